"""Stage runners: read the input files, call the pure stage function, write
the outputs atomically. The CLI commands and ``retarget run`` both call these.

One module per stage; each runner returns the list of files it wrote.
"""

from ..methods.regions import REGION_PRESETS_68, region_points, region_specs  # noqa: F401
from .apply import run_apply  # noqa: F401
from .auto_pose import run_auto_pose  # noqa: F401
from .decompose import run_decompose  # noqa: F401
from .edit import run_edit  # noqa: F401
from .pose import run_pose  # noqa: F401
from .select import TEMPLATE_MARK, run_select  # noqa: F401
from .solve_rig import run_solve_rig  # noqa: F401
from .track import run_import, run_track, run_train_tracker  # noqa: F401
