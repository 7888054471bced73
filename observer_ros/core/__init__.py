# observer_ros.core: the ROS-free core (numpy, scipy and python-control only).
"""
The ROS-free core of observer_ros: model, analysis, design, compensator, estimators.

Nothing here imports rclpy or any ROS package (a test checks it).

"""

from .analysis import *     # noqa: F401,F403
from .analysis import __all__ as _analysis_all
from .closed_loop import *  # noqa: F401,F403
from .closed_loop import __all__ as _closed_loop_all
from .design import *       # noqa: F401,F403
from .design import __all__ as _design_all
from .errors import *       # noqa: F401,F403
from .errors import __all__ as _errors_all
from .estimators import *   # noqa: F401,F403
from .estimators import __all__ as _estimators_all
from .gramians import *     # noqa: F401,F403
from .gramians import __all__ as _gramians_all
from .innovation import *   # noqa: F401,F403
from .innovation import __all__ as _innovation_all
from .model import *        # noqa: F401,F403
from .model import __all__ as _model_all
from .simulate import *     # noqa: F401,F403
from .simulate import __all__ as _simulate_all
from .spec import *         # noqa: F401,F403
from .spec import __all__ as _spec_all
from .vehicle_design import *  # noqa: F401,F403
from .vehicle_design import __all__ as _vehicle_design_all
from .vehicle_report import *  # noqa: F401,F403
from .vehicle_report import __all__ as _vehicle_report_all

__all__ = (list(_errors_all) + list(_model_all) + list(_spec_all) + list(_analysis_all)
           + list(_gramians_all)
           + list(_design_all) + list(_closed_loop_all) + list(_vehicle_design_all)
           + list(_vehicle_report_all) + list(_estimators_all)
           + list(_simulate_all) + list(_innovation_all))
