"""Registration of the robot in a stereo camera: 9D pose, the paper's costs, CSO and SDR.

``T_cam_base`` (base frame → left OpenCV optical frame, metres) is the unknown; the right camera
follows through the fixed ``T_right_left``. :func:`cso` initialises it by a swarm of virtual
cameras, :func:`sdr` / :func:`sdr_multistart` refine it by stereo differentiable rendering
(AdamW, then an L-BFGS polish for the last fraction of a millimetre; optionally letting each
segmentation's boundary shift by a fitted offset, so masks that are uniformly too fat or too
thin do not bias the depth: ``SDRConfig.boundary_offset``; and holding the distance to the
masks' stereo centroid disparity, which a blurry mask's outline cannot shift:
``SDRConfig.disparity_weight``);
:func:`sdr_with_prior` alternates a 4-channel segmentation (prior = render at the estimate) with
SDR; :func:`register` drives it all on a recording. When the masks show several robots, each
is fitted on the pixels near its own estimate, and fitted again without another robot's pixels
when that robot's joints explain its first fit better (``RegisterConfig.other_robots_margin``).
:mod:`roboseg.registration.self_training` (imported on its own, as it needs the training stack)
fine-tunes a segmenter on the recording's frames labelled by an estimate and registers again.
"""

from roboseg.registration.cso import Candidate, CSOConfig, CSOResult, cso
from roboseg.registration.losses import RegistrationTarget, distance_mse_loss, exp_dice_loss
from roboseg.registration.pose import look_at_T_cam_base, matrix_to_pose9d, pose9d_to_matrix
from roboseg.registration.register import RegisterConfig, Registration, register
from roboseg.registration.sdr import RegistrationResult, SDRConfig, sdr, sdr_multistart
from roboseg.registration.sdr_prior import PriorConfig, PriorResult, sdr_with_prior
from roboseg.registration.views import View, stereo_views

__all__ = [
    "CSOConfig",
    "CSOResult",
    "Candidate",
    "PriorConfig",
    "PriorResult",
    "RegisterConfig",
    "Registration",
    "RegistrationResult",
    "RegistrationTarget",
    "SDRConfig",
    "View",
    "cso",
    "distance_mse_loss",
    "exp_dice_loss",
    "look_at_T_cam_base",
    "matrix_to_pose9d",
    "pose9d_to_matrix",
    "register",
    "sdr",
    "sdr_multistart",
    "sdr_with_prior",
    "stereo_views",
]
