"""Where the Hydra configuration tree lives, shared by every ``roboseg-*`` command.

The configs are the top-level ``conf/`` folder of the source checkout (the editable install that
``make`` sets up points here). ``$ROBOSEG_CONF_DIR`` overrides it, e.g. for a copied tree.
"""

from __future__ import annotations

import os
from pathlib import Path

CONF_ENV = "ROBOSEG_CONF_DIR"

#: Absolute path of the configuration directory, as Hydra's ``config_path`` wants it.
CONF_DIR: str = os.environ.get(CONF_ENV) or str(Path(__file__).resolve().parents[2] / "conf")
