"""
The ``estimator`` node: a Kalman filter on ``measurement``, estimates and predictions out.

Subscribes ``measurement`` (geometry_msgs/PoseWithCovarianceStamped, best-effort
depth 10, so it matches reliable and best-effort publishers). dt comes from the
message stamps, never from arrival times. After each fused measurement it publishes
``estimate`` (nav_msgs/Odometry, stamped with the measurement's stamp) and
``prediction`` (the state ``horizon_s`` ahead, stamped stamp + horizon_s).
All the mathematics is in :mod:`kf_train.core.estimator`.
"""

import dataclasses

from geometry_msgs.msg import PoseWithCovarianceStamped
from kf_train import messages
from kf_train.core.estimator import EstimatorSettings, INITIALIZATIONS, TrainEstimator
from kf_train.parameters import BIG, declare
from kf_train.runner import run, StartupError
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

QOS_DEPTH = 10
WARN_THROTTLE_S = 5.0
DEFAULTS = EstimatorSettings()
FRAME_PARAMETERS = ('frame_id', 'child_frame_id')


class EstimatorNode(Node):
    """Estimates the train's position and velocity and predicts them horizon_s ahead."""

    def __init__(self, **kwargs):
        """Declare parameters, build the filter and wire the topics."""
        super().__init__('estimator', **kwargs)
        live = 'Takes effect from the next measurement.'
        at_init = 'Used when the filter (re)initialises.'
        values = {
            'initial_state': declare(
                self, 'initial_state', list(DEFAULTS.initial_state),
                'Initial [position m, velocity m/s]; in first_measurement mode only the '
                'velocity is used. ' + at_init, constraints='2 finite doubles'),
            'initial_covariance': declare(
                self, 'initial_covariance', list(DEFAULTS.initial_covariance),
                'Initial covariance [m², m²/s²]: the diagonal (2 values) or the full '
                'row-major matrix (4 values), symmetric positive semi-definite. ' + at_init,
                constraints='2 or 4 finite doubles, symmetric PSD'),
            'process_noise_density': declare(
                self, 'process_noise_density', DEFAULTS.process_noise_density,
                'White-noise acceleration density q [m²/s³]: Q(dt) = q [[dt³/3, dt²/2], '
                '[dt²/2, dt]]. 0 (seed 000) trusts the constant-velocity model fully. '
                + live, float_range=(0.0, BIG)),
            'measurement_variance': declare(
                self, 'measurement_variance', DEFAULTS.measurement_variance,
                'Measurement variance R [m²] overriding the message covariance[0]; '
                '0 uses the message. ' + live, float_range=(0.0, BIG)),
            'horizon_s': declare(
                self, 'horizon_s', DEFAULTS.horizon_s,
                'How far ahead the prediction is [s]. ' + live,
                float_range=(0.0, 86400.0)),
            'initialization': declare(
                self, 'initialization', DEFAULTS.initialization,
                'first_measurement: the first measurement sets the position, the velocity '
                'starts wide; prior: initial_state/initial_covariance hold '
                'nominal_period_s before the first stamp (seed 000). ' + at_init,
                constraints='one of: ' + ', '.join(INITIALIZATIONS)),
            'nominal_period_s': declare(
                self, 'nominal_period_s', DEFAULTS.nominal_period_s,
                'Prior mode: how long before the first stamp the prior holds [s]. '
                + at_init, float_range=(1e-6, 3600.0)),
            'first_velocity_std_mps': declare(
                self, 'first_velocity_std_mps', DEFAULTS.first_velocity_std_mps,
                'first_measurement mode: standard deviation of the initial velocity '
                '[m/s]. ' + at_init, float_range=(1e-6, 1e6)),
        }
        self.frame_id = declare(self, 'frame_id', 'odom',
                                'header.frame_id of estimate and prediction (REP 105).',
                                constraints='a non-empty frame name')
        self.child_frame_id = declare(self, 'child_frame_id', 'base_link',
                                      'child_frame_id of estimate and prediction.',
                                      constraints='a non-empty frame name')
        try:
            settings = EstimatorSettings(
                **{name: _setting_value(name, value) for name, value in values.items()})
            self.estimator = TrainEstimator(settings)
        except ValueError as error:
            raise StartupError(f'invalid parameter: {error}') from None
        if not self.frame_id or not self.child_frame_id:
            raise StartupError('invalid parameter: frame_id and child_frame_id must not '
                               'be empty')
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.received = 0
        self.fused = 0
        self.rejected = 0
        qos = QoSProfile(depth=QOS_DEPTH, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.subscription = self.create_subscription(
            PoseWithCovarianceStamped, 'measurement', self._on_measurement, qos)
        self.estimate_pub = self.create_publisher(Odometry, 'estimate', QOS_DEPTH)
        self.prediction_pub = self.create_publisher(Odometry, 'prediction', QOS_DEPTH)

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        """Validate a change as a whole; apply it only if all of it is valid."""
        changes = {}
        frames = {}
        for parameter in parameters:
            if parameter.name in FRAME_PARAMETERS:
                if not parameter.value:
                    return SetParametersResult(
                        successful=False, reason=f'{parameter.name} must not be empty')
                frames[parameter.name] = parameter.value
            elif hasattr(DEFAULTS, parameter.name):
                changes[parameter.name] = _setting_value(parameter.name, parameter.value)
        try:
            settings = dataclasses.replace(self.estimator.settings, **changes).validated()
        except ValueError as error:
            return SetParametersResult(successful=False, reason=str(error))
        self.estimator.reconfigure(settings)
        for name, value in frames.items():
            setattr(self, name, value)
        return SetParametersResult(successful=True)

    def _on_measurement(self, msg: PoseWithCovarianceStamped) -> None:
        """Fuse one measurement and publish the estimate and the prediction."""
        self.received += 1
        measurement = messages.from_measurement_msg(msg)
        try:
            step = self.estimator.process(measurement.stamp_ns, measurement.position_m,
                                          measurement.variance_m2)
        except ValueError as error:
            self.rejected += 1
            self.get_logger().warning(f'measurement rejected: {error}',
                                      throttle_duration_sec=WARN_THROTTLE_S)
            return
        self.fused += 1
        self.estimate_pub.publish(messages.to_state_odometry_msg(
            step.stamp_ns, self.frame_id, self.child_frame_id, step.x, step.P))
        self.prediction_pub.publish(messages.to_state_odometry_msg(
            step.prediction_stamp_ns, self.frame_id, self.child_frame_id,
            step.predicted_x, step.predicted_P))


def _setting_value(name: str, value):
    """Return a parameter value in the form EstimatorSettings keeps it."""
    if name in ('initial_state', 'initial_covariance'):
        return tuple(float(v) for v in value)
    return value


def main(args=None) -> int:
    """Run the estimator until Ctrl-C or SIGTERM."""
    return run(EstimatorNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
