# observer_ros.core: the ROS-free core (numpy, scipy and python-control only).
"""
The ROS-free core of observer_ros: model, analysis, design, compensator, estimators.

Nothing here imports rclpy or any ROS package (a test checks it).

The names below are importable from ``observer_ros.core``; each submodule is imported
when one of its names is first asked for, so a process imports only what it uses (a
node that steps an estimator does not import the design report's python-control and
scipy.signal). ``from observer_ros.core.X import name`` imports X alone.

"""

from ._lazy import exports

# the submodule that defines each exported name, in the order of __all__
_EXPORTS = {
    'errors': ('ObserverError', 'DimensionError', 'NotObservableError', 'NotDetectableError',
               'NotControllableError', 'DesignError', 'VehicleFileError',
               'ObserverDesignWarning', 'DesignVerificationError', 'error_text',
               'quiet_on_closed_pipe', 'CLOSED_PIPE_STATUS'),
    'model': ('as_matrix', 'as_vector', 'as_poles', 'Plant', 'zoh_matrices',
              'map_poles_to_discrete'),
    'spec': ('SensorSpec', 'ObserverSpec', 'ControllerSpec', 'SimulatorSpec', 'Vehicle',
             'OBSERVER_TYPES', 'SENSOR_TYPES', 'HISTORY_LENGTH'),
    'analysis': ('obsv', 'ctrb', 'numerical_rank', 'rank_tolerance', 'PBHResult', 'pbh_test',
                 'pbh_test_controllability', 'observable_decomposition',
                 'controllable_decomposition', 'unobservable_eigenvalues',
                 'uncontrollable_eigenvalues', 'Mode', 'ObservabilityReport',
                 'observability_report', 'ControllabilityReport', 'controllability_report',
                 'is_observable', 'is_detectable', 'is_controllable', 'is_stabilizable',
                 'is_stable_eigenvalue', 'stability_margin', 'format_complex', 'PBH_TOL_FACTOR'),
    'gramians': ('observability_gramian', 'controllability_gramian'),
    'design': ('observer_gain', 'controller_gain', 'lqr_gain', 'kalman_gain',
               'kalman_update_gain', 'pole_placement_error', 'reduced_coordinates',
               'ReducedOrderDesign', 'reduced_order_observer', 'PLACEMENT_WARN_TOL',
               'ACKER_DIGITS_LOST'),
    'closed_loop': ('closed_loop_matrix', 'closed_loop_matrices', 'error_dynamics_matrix',
                    'reduced_closed_loop_matrix', 'reduced_closed_loop_matrices',
                    'spectrum_match', 'separation_check', 'compensator_matrices',
                    'compensator_ss', 'compensator_tf', 'compensator_poles',
                    'reference_input_matrix', 'tracking_residual', 'tracking_ok',
                    'plant_matrices', 'separation_details', 'SEPARATION_TOL'),
    'vehicle_design': ('observer_noise_gain', 'design_warnings', 'VehicleDesign',
                       'design_vehicle', 'measurement_intensity', 'SPEED_RATIO',
                       'NOISE_GAIN_LIMIT'),
    'vehicle_report': ('to_json_dict', 'format_report'),
    'estimators': ('DT_DIGITS', 'GAIN_DIGITS', 'CACHE_SIZE', 'GAIN_CACHE_SIZE', 'TimeOrderError',
                   'StepCache', 'Estimator', 'FullOrderEstimator', 'ReducedOrderEstimator',
                   'OpenLoopEstimator', 'KalmanEstimator', 'make_estimator',
                   'process_noise_covariance', 'History', 'HISTORY_MAX_MESSAGES',
                   'CHECKPOINT_EVERY', 'DENSE_DEPTH', 'DENSE_FOR'),
    'simulate': ('PlantSimulator', 'process_noise_factor'),
    'innovation': ('InnovationMonitor', 'SensorHealth', 'whiten', 'ljung_box', 'ljung_box_acf',
                   'ljung_box_of_products', 'nis_bounds', 'sequence_health',
                   'sequence_health_blocks', 'transient_time', 'WINDOW', 'LAGS', 'ALPHA',
                   'OTHER_MARGIN'),
}

__all__, __getattr__, __dir__ = exports(globals(), _EXPORTS)
