"""Draped operating-room simulator: writes the recordings a real stereo rig would.

:func:`simulate_recording` renders one or two robots (any URDF) moving on smooth random
trajectories, undraped and then draped in place, in a randomised room with occluders and drifting
light, and writes stereo JPEGs, camera infos, joint states, the calibration on ``/tf_static`` and
ground-truth masks to an MCAP file.
"""

from roboseg.sim.simulate import SIM_METADATA, SimConfig, SimSummary, simulate_recording

__all__ = ["SIM_METADATA", "SimConfig", "SimSummary", "simulate_recording"]
