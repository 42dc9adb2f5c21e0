"""
The production features of the nodes (issue 21), in process.

Lifecycle (``managed``), QoS overrides and incompatible-QoS reports, stale inputs in
``/diagnostics`` (the ``<node>: inputs`` status), the gate's reach and the throttled
rejection line. Every wait is a bounded spin.
"""

import copy
import math

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from kf_train.estimator import EstimatorSettings, NS_PER_S, Rejected, StreamEstimator
from kf_train.ros import messages
from kf_train.ros.diagnostics import gate_reach_m
from kf_train.ros.estimator_node import EstimatorNode
from kf_train.ros.input_watch import InputWatch, watch_period_s
from kf_train.ros.lifecycle import managed_class, managed_requested, SUCCESS
from kf_train.ros.simulator_node import SimulatorNode
from nav_msgs.msg import Odometry
import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import own_node, spin_until

PERIOD_NS = 100_000_000


def _parameters(values):
    """Return rclpy Parameters of a dict."""
    return [Parameter(name, value=value) for name, value in values.items()]


class Probe:
    """A node that publishes measurements and records estimates and /diagnostics."""

    def __init__(self, context, executor, reliability=ReliabilityPolicy.RELIABLE):
        """Create the probe's publisher and subscriptions on ``executor``."""
        node = self.node = rclpy.create_node('probe', context=context)
        self.pub = node.create_publisher(
            PoseWithCovarianceStamped, 'measurement',
            QoSProfile(depth=100, reliability=reliability))
        self.estimates, self.diagnostics, self.ground_truth = [], [], []
        node.create_subscription(Odometry, 'estimate', self.estimates.append, 1000)
        node.create_subscription(Odometry, 'ground_truth', self.ground_truth.append, 1000)
        node.create_subscription(DiagnosticArray, '/diagnostics', self.diagnostics.append, 100)
        executor.add_node(node)
        own_node(node)
        self.stamp_ns = 10 * NS_PER_S

    def send(self, position_m: float = None) -> None:
        """Publish the next measurement (on a train at 10 m/s unless given)."""
        self.stamp_ns += PERIOD_NS
        if position_m is None:
            position_m = 10.0 * self.stamp_ns / NS_PER_S
        self.pub.publish(messages.to_measurement_msg(self.stamp_ns, 'odom', position_m, 1.0))

    def inputs_status(self):
        """Return the newest '<node>: inputs' status, or None."""
        for array in reversed(self.diagnostics):
            for status in array.status:
                if status.name.endswith(': inputs'):
                    return status
        return None


def _start(executor, node):
    """Add ``node`` to the executor and own it."""
    executor.add_node(node)
    own_node(node)
    return node


# -- lifecycle ----------------------------------------------------------------------------

def test_managed_requested_reads_the_command_line(tmp_path):
    """-p managed:=true and a params file's managed are seen before the node exists."""
    assert not managed_requested(['estimator'], 'estimator')
    assert managed_requested(['x', '--ros-args', '-p', 'managed:=true'], 'estimator')
    assert not managed_requested(['x', '--ros-args', '-p', 'managed:=false'], 'estimator')
    assert not managed_requested(['x', '-p', 'managed:=true'], 'estimator')  # not a ROS arg
    params = tmp_path / 'p.yaml'
    params.write_text('estimator:\n  ros__parameters:\n    managed: true\n')
    assert managed_requested(['x', '--ros-args', '--params-file', str(params)], 'estimator')
    assert not managed_requested(['x', '--ros-args', '--params-file', str(params)],
                                 'simulator')
    assert not managed_requested(['x', '--ros-args', '--params-file', str(params), '-p',
                                  'managed:=false'], 'estimator')
    params.write_text('/**:\n  ros__parameters:\n    managed: true\n')  # as launch_ros writes
    assert managed_requested(['x', '--ros-args', '--params-file', str(params)], 'simulator')
    assert not managed_requested(['x', '--ros-args', '--params-file', '/nonexistent.yaml'],
                                 'estimator')


def test_managed_estimator_goes_through_every_transition(ros_context, executor):
    """Unconfigured: nothing; configure: interfaces; activate: fuses; cleanup; again."""
    node = _start(executor, managed_class(EstimatorNode)(context=ros_context))
    probe = Probe(ros_context, executor)
    assert not node.has_parameter('preset') and not hasattr(node, 'session')
    assert node.trigger_configure() == SUCCESS
    assert node.get_parameter('managed').value is False  # declared, as any parameter
    assert spin_until(executor, lambda: probe.pub.get_subscription_count() == 1)
    probe.send()
    spin_until(executor, lambda: False, timeout_s=0.3)   # inactive: not taken
    assert node.received == 0
    assert node.trigger_activate() == SUCCESS
    probe.send()
    assert spin_until(executor, lambda: node.fused == 1 and len(probe.estimates) == 1)
    assert node.trigger_deactivate() == SUCCESS
    probe.send()
    spin_until(executor, lambda: False, timeout_s=0.3)
    assert node.received == 1
    assert node.trigger_cleanup() == SUCCESS
    assert node.count_subscribers('estimate') == 1  # the probe's only
    assert spin_until(executor, lambda: probe.pub.get_subscription_count() == 0)
    assert node.trigger_configure() == SUCCESS          # re-configure after cleanup
    assert node.trigger_activate() == SUCCESS
    assert spin_until(executor, lambda: probe.pub.get_subscription_count() == 1)
    probe.send()
    assert spin_until(executor, lambda: node.fused == 1)  # a fresh session
    assert not node.done.done()
    assert node.trigger_shutdown() == SUCCESS
    assert node.done.done()


def test_invalid_parameter_fails_configure_with_its_reason(ros_context, executor):
    """A bad parameter fails configure (back to unconfigured) with one log line."""
    node = _start(executor, managed_class(EstimatorNode)(
        context=ros_context, parameter_overrides=_parameters({'stale_warn_periods': 20.0})))
    lines = []

    class Logger:
        def error(self, text):
            lines.append(text)

    node.get_logger = Logger
    assert node.trigger_configure() != SUCCESS
    assert len(lines) == 1 and 'stale_error_periods' in lines[0], lines
    assert '\n' not in lines[0]
    assert list(node.subscriptions) == []


def test_managed_simulator_publishes_only_while_active(ros_context, executor):
    """The simulator samples only while active."""
    node = _start(executor, managed_class(SimulatorNode)(
        context=ros_context, parameter_overrides=_parameters({'rate_hz': 50.0})))
    probe = Probe(ros_context, executor)
    assert node.trigger_configure() == SUCCESS
    assert spin_until(executor, lambda: node.truth_pub.get_subscription_count() == 1)
    spin_until(executor, lambda: False, timeout_s=0.3)
    assert node.published == 0
    assert node.trigger_activate() == SUCCESS
    assert spin_until(executor, lambda: len(probe.ground_truth) >= 3)
    assert node.trigger_deactivate() == SUCCESS
    published = node.published
    spin_until(executor, lambda: False, timeout_s=0.3)
    assert node.published == published
    assert node.trigger_shutdown() == SUCCESS and node.done.done()


# -- QoS ------------------------------------------------------------------------------------

def test_qos_overrides_are_parameters_starting_from_qos_reliability(ros_context):
    """qos_overrides.* exist; qos_reliability is their default; an override wins."""
    node = own_node(EstimatorNode(context=ros_context))
    name = 'qos_overrides./measurement.subscription.reliability'
    assert node.get_parameter(name).value == 'best_effort'
    assert node.get_parameter('qos_overrides./measurement.subscription.depth').value == 10
    assert node.describe_parameter(name).read_only
    assert node.get_parameter('qos_overrides./estimate.publisher.reliability').value == \
        'reliable'
    node = own_node(EstimatorNode(context=ros_context, parameter_overrides=_parameters(
        {'qos_reliability': 'reliable', 'qos_depth': 7})))
    assert node.get_parameter(name).value == 'reliable'
    assert node.subscription.qos_profile.depth == 7
    node = own_node(EstimatorNode(context=ros_context, parameter_overrides=_parameters(
        {name: 'reliable'})))
    assert node.subscription.qos_profile.reliability == ReliabilityPolicy.RELIABLE


def test_incompatible_publisher_is_logged_and_in_diagnostics(ros_context, executor):
    """A best-effort publisher to a reliable subscription: named with its policy."""
    node = _start(executor, EstimatorNode(context=ros_context, parameter_overrides=_parameters(
        {'qos_reliability': 'reliable', 'diagnostics_period_s': 0.05})))
    probe = Probe(ros_context, executor, reliability=ReliabilityPolicy.BEST_EFFORT)
    assert spin_until(executor, lambda: ('/measurement', 'RELIABILITY') in
                      node.watch.qos_incompatible, timeout_s=20.0)
    assert spin_until(executor, lambda: probe.inputs_status() is not None and
                      'RELIABILITY' in probe.inputs_status().message)
    status = probe.inputs_status()
    assert status.level == DiagnosticStatus.WARN
    assert 'incompatible QoS on /measurement: RELIABILITY' in status.message
    assert probe.pub.get_subscription_count() == 0


# -- stale inputs ---------------------------------------------------------------------------

def test_input_watch_levels():
    """OK, WARN after warn periods, ERROR after error periods, OK on a new message."""
    watch = InputWatch(['/measurement'])
    assert watch.check({'/measurement': 0}, 0.0, 0.1, 3, 10) == []  # never: not watched
    assert watch.check({'/measurement': 1}, 1.0, 0.1, 3, 10) == []
    assert watch.check({'/measurement': 1}, 1.29, 0.1, 3, 10) == []
    [(topic, level, line)] = watch.check({'/measurement': 1}, 1.3, 0.1, 3, 10)
    assert (topic, level) == ('/measurement', 'WARN') and '0.300 s' in line
    [(_, level, _)] = watch.check({'/measurement': 1}, 2.0, 0.1, 3, 10)
    assert level == 'ERROR' and watch.stale == ('/measurement',)
    status = watch.status(2.0, 0.1)
    assert status.level == 'ERROR' and '/measurement stale' in status.message
    assert ('/measurement.age_s', '1.000') in status.values
    [(_, level, _)] = watch.check({'/measurement': 2}, 2.1, 0.1, 3, 10)
    assert level == 'OK' and watch.status(2.1, 0.1).level == 'OK'
    assert watch_period_s(0.001) == 0.005 and watch_period_s(0.1) == 0.05
    assert watch_period_s(100.0) == 1.0


def test_stale_measurement_reaches_error_then_ok(ros_context, executor):
    """Silence: ERROR within error periods (+ a check); messages again: OK."""
    period_s, error_periods = 0.05, 6
    node = _start(executor, EstimatorNode(context=ros_context, parameter_overrides=_parameters(
        {'expected_period_s': period_s, 'stale_warn_periods': 2.0,
         'stale_error_periods': float(error_periods), 'diagnostics_period_s': 10.0})))
    probe = Probe(ros_context, executor)
    assert spin_until(executor, lambda: probe.pub.get_subscription_count() == 1)
    for _ in range(3):
        count = node.received
        probe.send()
        assert spin_until(executor, lambda: node.received == count + 1)
    assert spin_until(executor, lambda: node.watch.topics and not node.watch.stale)
    levels = []
    start = node.get_clock().now().nanoseconds
    assert spin_until(executor, lambda: probe.inputs_status() is not None and (
        levels.append(probe.inputs_status().level) or
        probe.inputs_status().level == DiagnosticStatus.ERROR), timeout_s=10.0)
    waited_s = (node.get_clock().now().nanoseconds - start) / NS_PER_S
    # Error periods, plus one check period and a scheduling margin.
    assert waited_s < (error_periods + 1) * period_s + 0.5, waited_s
    assert DiagnosticStatus.WARN in levels
    assert '/measurement stale' in probe.inputs_status().message
    assert '/measurement.age_s' in {kv.key for kv in probe.inputs_status().values}
    probe.send()
    assert spin_until(executor, lambda: probe.inputs_status().level == DiagnosticStatus.OK)


def test_stale_output_predict_publishes_a_widening_estimate(ros_context, executor):
    """stale_output predict: while stale, estimates at now with a growing variance."""
    _start(executor, EstimatorNode(context=ros_context, parameter_overrides=_parameters(
        {'expected_period_s': 0.05, 'stale_warn_periods': 1.0, 'stale_error_periods': 2.0,
         'stale_output': 'predict', 'preset': 'train', 'process_noise_density': 1.0})))
    probe = Probe(ros_context, executor)
    assert spin_until(executor, lambda: probe.pub.get_subscription_count() == 1)
    for _ in range(3):
        count = len(probe.estimates)
        probe.send()
        assert spin_until(executor, lambda: len(probe.estimates) == count + 1)
    fused = len(probe.estimates)
    assert spin_until(executor, lambda: len(probe.estimates) >= fused + 3)
    variances = [msg.pose.covariance[0] for msg in probe.estimates[fused - 1:]]
    assert all(b > a for a, b in zip(variances, variances[1:])), variances


def test_the_absolute_band_is_published_fused_and_stale(ros_context, executor):
    """covariance_reference absolute (rail): P + 6 × the fix's variance, stale ones too."""
    _start(executor, EstimatorNode(context=ros_context, parameter_overrides=_parameters(
        {'expected_period_s': 0.05, 'stale_warn_periods': 1.0, 'stale_error_periods': 2.0,
         'stale_output': 'predict', 'covariance_reference': 'absolute'})))
    probe = Probe(ros_context, executor)
    assert spin_until(executor, lambda: probe.pub.get_subscription_count() == 1)
    for _ in range(3):
        count = len(probe.estimates)
        probe.send()                          # variance 1 m²: B = 6 m²
        assert spin_until(executor, lambda: len(probe.estimates) == count + 1)
    fused = len(probe.estimates)
    assert spin_until(executor, lambda: len(probe.estimates) >= fused + 2)
    variances = [msg.pose.covariance[0] for msg in probe.estimates]
    # The filter's own P_pp is at most the fix's 1 m² after a fix, and grows when stale.
    assert all(6.0 < v <= 7.0 for v in variances[:fused]), variances
    assert all(v > 6.0 for v in variances[fused:]), variances


def test_stale_control_withholds_the_estimate_until_it_returns(ros_context, executor):
    """stale_output stop: with the car's control silent, new estimates are withheld."""
    node = _start(executor, EstimatorNode(context=ros_context, parameter_overrides=_parameters(
        {'preset': 'car', 'expected_period_s': 0.05, 'stale_warn_periods': 1.0,
         'stale_error_periods': 2.0})))
    probe = Probe(ros_context, executor)
    kind, control_msg, _ = messages.CONTROL_MESSAGES['acceleration']
    control_pub = probe.node.create_publisher(kind, 'control', QoSProfile(depth=100))
    assert spin_until(executor, lambda: probe.pub.get_subscription_count() == 1
                      and control_pub.get_subscription_count() == 1)

    def send(with_control):
        count = node.received
        if with_control:
            control_pub.publish(control_msg(probe.stamp_ns + PERIOD_NS, 'base_link', 1.0))
        probe.send(position_m=1.0)
        assert spin_until(executor, lambda: node.received == count + 1)

    for _ in range(3):
        send(with_control=True)
    assert spin_until(executor, lambda: len(probe.estimates) == 3)
    assert spin_until(executor, lambda: '/control' in node.watch.stale)
    send(with_control=False)
    spin_until(executor, lambda: False, timeout_s=0.2)
    assert len(probe.estimates) == 3 and node.fused == 4  # fused, not published
    send(with_control=True)
    assert spin_until(executor, lambda: '/control' not in node.watch.stale)
    send(with_control=True)
    assert spin_until(executor, lambda: len(probe.estimates) >= 4)


def test_a_silent_velocity_is_watched_but_never_withholds_the_estimate(ros_context, executor):
    """The rail default's velocity topic goes stale like any input; positions go on."""
    node = _start(executor, EstimatorNode(context=ros_context, parameter_overrides=_parameters(
        {'expected_period_s': 0.05, 'stale_warn_periods': 1.0, 'stale_error_periods': 2.0})))
    probe = Probe(ros_context, executor)
    velocity_pub = probe.node.create_publisher(
        messages.VELOCITY_MESSAGES['twist_with_covariance'], 'velocity', QoSProfile(depth=100))
    assert spin_until(executor, lambda: probe.pub.get_subscription_count() == 1
                      and velocity_pub.get_subscription_count() == 1)
    assert node.watch.topics[-1].endswith('/velocity')

    def send(with_velocity):
        count, speeds = node.received, node.session.velocities_received
        probe.send()
        if with_velocity:
            msg = messages.VELOCITY_MESSAGES['twist_with_covariance']()
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(probe.stamp_ns, NS_PER_S)
            msg.twist.twist.linear.x = 10.0
            msg.twist.covariance[0] = 0.04
            velocity_pub.publish(msg)
        assert spin_until(executor, lambda: node.received == count + 1 and
                          node.session.velocities_received == speeds + with_velocity)

    for _ in range(3):
        send(with_velocity=True)
    assert spin_until(executor, lambda: len(probe.estimates) >= 3)
    assert spin_until(executor, lambda: any(name.endswith('/velocity')
                                            for name in node.watch.stale))
    published = len(probe.estimates)
    send(with_velocity=False)
    assert spin_until(executor, lambda: len(probe.estimates) == published + 1)
    send(with_velocity=True)
    assert spin_until(executor, lambda: not any(name.endswith('/velocity')
                                                for name in node.watch.stale))


# -- the gate's reach -----------------------------------------------------------------------

@pytest.mark.parametrize('preset', ['train', 'rail'])
def test_gate_reach_is_the_smallest_rejected_jump(preset):
    """A jump 0.1 % beyond the reach is rejected, 0.1 % short of it is fused."""
    estimator = StreamEstimator(EstimatorSettings(preset=preset, process_noise_density=(
        0.5 if preset == 'train' else 0.0)))
    stamp = NS_PER_S
    for k in range(20):
        stamp += PERIOD_NS
        estimator.process(stamp, 10.0 * k * 0.1, 1.0)
    now = stamp + 3 * PERIOD_NS
    reach = gate_reach_m(estimator, now, (1.0,))
    x, P = estimator.predict_to(now)
    center = float(x[0])
    if preset == 'train':
        assert reach == pytest.approx(math.sqrt(estimator.gate_threshold * (P[0, 0] + 1.0)))
    else:  # the IMM's predicted measurement: its prior mixture's (z = 0: y = -ẑ)
        before = estimator.state
        center = -float(estimator.model.predict_update(
            *before, 0.3, np.zeros(1), np.eye(1))[2].innovation[0])
        assert all((a == b).all() for a, b in zip(before, estimator.state))  # unchanged
    for factor, rejected in ((1.001, True), (0.999, False)):
        trial = copy.deepcopy(estimator)
        try:
            trial.process(now, center + factor * reach, 1.0)
            assert not rejected, factor
        except Rejected as rejection:
            assert rejected and rejection.reason == 'outlier', (factor, rejection)


def test_gate_reach_is_in_diagnostics(ros_context, executor):
    """/diagnostics carries gate_reach_m once there is a state."""
    node = _start(executor, EstimatorNode(context=ros_context, parameter_overrides=_parameters(
        {'diagnostics_period_s': 0.05})))
    probe = Probe(ros_context, executor)
    assert spin_until(executor, lambda: probe.pub.get_subscription_count() == 1)
    for _ in range(3):
        count = node.fused
        probe.send()
        assert spin_until(executor, lambda: node.fused == count + 1)

    def reach():
        for array in reversed(probe.diagnostics):
            values = {kv.key: kv.value for kv in array.status[0].values}
            if 'gate_reach_m' in values:
                return float(values['gate_reach_m'])
        return None
    assert spin_until(executor, lambda: reach() is not None)
    assert 0.0 < reach() < 1e3
    lines = []

    class Logger:
        def warning(self, text, **options):
            lines.append((text, options))

        info = warning

    node.get_logger = Logger
    count = node.rejected
    for _ in range(2):
        probe.send(position_m=1e6)
    assert spin_until(executor, lambda: node.rejected == count + 2)
    gated = [(text, options) for text, options in lines if text.startswith('gate rejected')]
    assert len(gated) == 2, lines  # rclpy's logger throttles them: one a second
    assert all(options == {'throttle_duration_sec': 1.0} for _, options in gated)
    assert 'NIS' in gated[0][0] and f'{node.estimator.gate_threshold:.4g}' in gated[0][0]
