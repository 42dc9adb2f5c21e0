"""
In-process tests of the estimator node: input contract, outputs, services, diagnostics, tuning.

Each test runs the node and a probe node on the test's own executor and context; the
probe publishes one measurement at a time and spins until the node has taken it, so
the best-effort subscription never drops one.
"""

import math
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped, Vector3Stamped
from kf_train.estimator import (
    DEFAULT_GATE_PROBABILITY, EstimateStep, EstimatorSettings, NS_PER_S, Rejected,
    REJECTION_REASONS, RESET_REASONS, StreamEstimator)
from kf_train.ros import messages
from kf_train.ros.diagnostics import MATCHED_KEYS
from kf_train.ros.estimator_node import EstimatorNode
from nav_msgs.msg import Odometry
import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from ros_helpers import own_node, spin_until
from rosgraph_msgs.msg import Clock
from std_srvs.srv import Trigger

PERIOD_NS = 100_000_000


class Harness:
    """An estimator node plus a probe node that feeds it and records what it publishes."""

    def __init__(self, context, executor, **parameters):
        """Start the node with ``parameters`` and wait until the probe is connected."""
        self.executor = executor
        self.node = EstimatorNode(context=context, parameter_overrides=[
            Parameter(name, value=value) for name, value in parameters.items()])
        probe = self.probe = rclpy.create_node('probe', context=context)
        self.measurement_pub = probe.create_publisher(PoseWithCovarianceStamped,
                                                      'measurement', 10)
        self.set_state_pub = probe.create_publisher(Odometry, '/estimator/set_state', 10)
        self.clock_pub = probe.create_publisher(Clock, '/clock', 10)
        self.outputs = {'estimate': [], 'prediction': [], 'innovation': [], 'diagnostics': []}
        for topic, kind in (('estimate', Odometry), ('prediction', Odometry),
                            ('innovation', Vector3Stamped)):
            probe.create_subscription(kind, topic, self.outputs[topic].append, 1000)
        probe.create_subscription(DiagnosticArray, '/diagnostics',
                                  self.outputs['diagnostics'].append, 100)
        self.reset_client = probe.create_client(Trigger, '/estimator/reset')
        self.parameters = AsyncParameterClient(probe, 'estimator')
        executor.add_node(self.node)
        executor.add_node(probe)
        own_node(self.node)
        own_node(probe)
        assert spin_until(executor, lambda: (
            self.measurement_pub.get_subscription_count() == 1
            and self.set_state_pub.get_subscription_count() == 1
            and self.node.estimate_pub.get_subscription_count() == 1
            and self.node.innovation_pub.get_subscription_count() == 1
            and self.reset_client.service_is_ready()), 10.0)

    def send(self, stamp_ns, position_m, variance_m2=1.0, frame_id='odom'):
        """Publish one measurement; return once the node took it and its outputs arrived."""
        received = self.node.received
        self.measurement_pub.publish(messages.to_measurement_msg(
            stamp_ns, frame_id, position_m, variance_m2))
        assert spin_until(self.executor, lambda: self.node.received == received + 1, 5.0)
        self.settle()

    def settle(self):
        """Spin until every estimate and innovation the node published has arrived."""
        node = self.node
        assert spin_until(self.executor, lambda: (
            len(self.outputs['estimate']) == node.fused
            and len(self.outputs['prediction']) == node.fused
            and len(self.outputs['innovation']) == node.innovations), 5.0)

    def diagnostics(self, newer_than=0.0):
        """Spin until a /diagnostics message published after ``newer_than`` arrives; return it."""
        def fresh():
            return [d for d in self.outputs['diagnostics']
                    if messages.stamp_to_ns(d.header.stamp) / NS_PER_S > newer_than]
        assert spin_until(self.executor, lambda: fresh(), 5.0)
        status = fresh()[-1].status[0]
        return status, {kv.key: kv.value for kv in status.values}

    def set_parameters(self, atomically=False, **values):
        """Set parameters through the parameter service (as ros2 param set); return results."""
        assert self.parameters.wait_for_services(5.0)
        call = (self.parameters.set_parameters_atomically if atomically
                else self.parameters.set_parameters)
        future = call([Parameter(name, value=value) for name, value in values.items()])
        assert spin_until(self.executor, future.done, 5.0)
        result = future.result()
        return [result.result] if atomically else result.results

    def all_published_numbers(self):
        """Return every float the node published on estimate, prediction and innovation."""
        numbers = []
        for msg in self.outputs['estimate'] + self.outputs['prediction']:
            numbers += [msg.pose.pose.position.x, msg.twist.twist.linear.x,
                        *msg.pose.covariance, *msg.twist.covariance]
        for msg in self.outputs['innovation']:
            numbers += [msg.vector.x, msg.vector.y, msg.vector.z]
        return numbers


def _now_ns():
    """Return the system clock, which the node clock follows without use_sim_time."""
    return time.time_ns()


def _good(k, base_ns):
    """Return (stamp, position) of good measurement k of a 10 m/s train, σ = 1 m."""
    noise = float(np.random.default_rng([17, k]).standard_normal())
    return base_ns + k * PERIOD_NS, 1.0 * k + noise


def test_every_bad_input_class_is_counted_and_never_published(ros_context, executor):
    """
    Each class of bad input is rejected and counted; the node keeps its state and runs on.

    With the node's defaults (the rail IMM, the χ² gate at 0.9999): the hostile-input
    contract holds for them.
    """
    h = Harness(ros_context, executor, expected_frame_id='odom')
    assert h.node.estimator.settings.preset == 'rail'
    base = _now_ns() - 60 * NS_PER_S
    twin = StreamEstimator(h.node.estimator.settings)
    for k in range(1, 21):
        h.send(*_good(k, base))
        twin.process(*_good(k, base), 1.0)
    newest = _good(20, base)[0]
    bad = [
        ('wrong_frame', {'stamp_ns': newest + 1, 'position_m': 20.0, 'frame_id': 'map'}),
        ('non_finite', {'stamp_ns': newest + 1, 'position_m': math.nan}),
        ('non_finite', {'stamp_ns': newest + 1, 'position_m': -math.inf}),
        ('non_finite', {'stamp_ns': newest + 1, 'position_m': 20.0, 'variance_m2': math.inf}),
        ('bad_variance', {'stamp_ns': newest + 1, 'position_m': 20.0, 'variance_m2': 0.0}),
        ('bad_variance', {'stamp_ns': newest + 1, 'position_m': 20.0, 'variance_m2': -2.0}),
        ('zero_stamp', {'stamp_ns': 0, 'position_m': 20.0}),
        ('future_stamp', {'stamp_ns': _now_ns() + 30 * NS_PER_S, 'position_m': 20.0}),
        ('duplicate_stamp', {'stamp_ns': newest, 'position_m': 20.0}),
        ('stale_stamp', {'stamp_ns': newest - 5 * NS_PER_S, 'position_m': 20.0}),
        ('outlier', {'stamp_ns': newest + PERIOD_NS, 'position_m': 500.0}),
    ]
    expected = dict.fromkeys(REJECTION_REASONS, 0)
    for reason, kwargs in bad:
        before = h.node.estimator.state
        fused = h.node.fused
        h.send(**{'variance_m2': 1.0, 'frame_id': 'odom', **kwargs})
        expected[reason] += 1
        assert h.node.estimator.stats().rejections == expected, reason
        assert h.node.fused == fused
        after = h.node.estimator.state
        assert after[0].tobytes() == before[0].tobytes(), reason
        assert after[1].tobytes() == before[1].tobytes(), reason
    for k in range(21, 31):
        h.send(*_good(k, base))
        step = twin.process(*_good(k, base), 1.0)
    assert np.array_equal(h.node.estimator.state[0], step.x)
    assert h.node.rejected == len(bad) and h.node.fused == 30
    assert all(math.isfinite(v) for v in h.all_published_numbers())
    # The gated outlier was published on innovation, with its NIS above the gate.
    assert max(m.vector.z for m in h.outputs['innovation']) > h.node.estimator.gate_threshold
    status, values = h.diagnostics(newer_than=time.time())
    for reason in REJECTION_REASONS:
        assert values[f'rejected.{reason}'] == str(expected[reason])
    assert values['rejected'] == str(len(bad)) and values['received'] == str(30 + len(bad))


def test_a_non_finite_state_is_never_published_and_resets(ros_context, executor):
    """Should the core ever return a non-finite state, the node resets instead of publishing."""
    h = Harness(ros_context, executor)
    base = _now_ns() - 60 * NS_PER_S
    h.send(*_good(1, base))
    real = h.node.estimator.process

    def broken(stamp_ns, *args, **kwargs):
        step = real(stamp_ns, *args, **kwargs)
        return step._replace(x=np.array([math.nan, 1.0]))

    h.node.estimator.process = broken
    h.send(*_good(2, base))
    assert h.node.estimator.stats().resets['non_finite'] == 1
    assert not h.node.estimator.initialized
    assert len(h.outputs['estimate']) == 1 and h.node.fused == 1
    h.node.estimator.process = real
    h.send(*_good(3, base))
    assert h.node.estimator.initialized and len(h.outputs['estimate']) == 2
    assert all(math.isfinite(v) for v in h.all_published_numbers())


def test_innovation_topic_layout(ros_context, executor):
    """The innovation topic carries x = y, y = S, z = NIS, stamped with the measurement."""
    h = Harness(ros_context, executor, preset='train', process_noise_density=0.2)
    base = _now_ns() - 60 * NS_PER_S
    twin = StreamEstimator(h.node.estimator.settings)
    results = []
    for k in (1, 2, 3, 5, 4):  # 4 comes late: its own stamp, not the newest
        h.send(*_good(k, base), variance_m2=0.5)
        step = twin.process(*_good(k, base), 0.5)
        if step.update is not None:
            results.append((step.measurement_stamp_ns, step.update))
    assert twin.stats().out_of_sequence == 1
    assert len(h.outputs['innovation']) == len(results) == 4
    for msg, (stamp, update) in zip(h.outputs['innovation'], results):
        assert messages.stamp_to_ns(msg.header.stamp) == stamp
        assert msg.header.frame_id == 'odom'
        assert msg.vector.x == update.innovation[0]
        assert msg.vector.y == update.innovation_covariance[0, 0]
        assert msg.vector.z == update.nis == pytest.approx(msg.vector.x ** 2 / msg.vector.y)
    # The estimate after the late one is republished at the newest stamp, corrected.
    last = h.outputs['estimate'][-1]
    assert messages.stamp_to_ns(last.header.stamp) == _good(5, base)[0]
    assert last.pose.pose.position.x == twin.state[0][0]


@pytest.mark.parametrize('variance_factor, verdict', [
    (1.0, None), (0.02, 'noise parameters too small'), (50.0, 'noise parameters too large')])
def test_diagnostics_judge_consistency(ros_context, executor, variance_factor, verdict):
    """The windowed mean NIS is checked against its χ² 99% bounds; R mis-set 50× is caught."""
    h = Harness(ros_context, executor, preset='train', gate_probability=1.0, nis_window=60,
                diagnostics_period_s=0.1, measurement_variance=variance_factor)
    rng = np.random.default_rng(4)
    base = _now_ns() - 60 * NS_PER_S
    for k in range(1, 62):
        h.send(base + k * PERIOD_NS, 1.0 * k + rng.standard_normal())
    status, values = h.diagnostics(newer_than=time.time())
    assert values['nis_window_count'] == '60'
    mean, lower, upper = (float(values[key]) for key in
                          ('nis_window_mean', 'nis_lower_99', 'nis_upper_99'))
    assert 0.0 < lower < 1.0 < upper
    if verdict is None:
        assert lower <= mean <= upper
        assert status.level == messages.DIAGNOSTIC_LEVELS['OK'] and status.message == 'ok'
    else:
        assert status.level == messages.DIAGNOSTIC_LEVELS['WARN']
        assert f'inconsistent: {verdict}' in status.message
    assert float(values['covariance_condition']) >= 1.0
    assert values['gate_threshold'] == 'inf' and values['initialized'] == 'true'


def test_diagnostics_report_rates_and_warn_once_on_timeout(ros_context, executor):
    """Diagnostics show the input rate and age; silence past timeout_s gives WARN, said once."""
    h = Harness(ros_context, executor, diagnostics_period_s=0.1, timeout_s=0.5)
    base = _now_ns() - 60 * NS_PER_S
    start = time.time()
    status, values = h.diagnostics(newer_than=start)
    assert values['last_measurement_age_s'] == 'never'
    assert status.message == 'waiting for measurements'
    for k in range(1, 11):
        h.send(*_good(k, base))
    status, values = h.diagnostics(newer_than=time.time())
    assert status.level == messages.DIAGNOSTIC_LEVELS['OK']
    assert float(values['last_measurement_age_s']) < 0.5
    assert float(values['input_rate_hz']) >= 0.0
    expected_keys = {'input_rate_hz', 'fused_rate_hz', 'received', 'fused', 'rejected',
                     'resets', 'reacquisitions', 'fused_out_of_sequence', 'gate_probability',
                     'covariance_condition', 'nis_window_count', 'set_state_refused'}
    expected_keys |= {f'rejected.{r}' for r in REJECTION_REASONS}
    expected_keys |= {f'resets.{r}' for r in RESET_REASONS}
    assert expected_keys <= set(values)
    # The harness's probe is the one publisher of measurement and the one subscriber of
    # estimate and prediction; a second subscriber is counted once DDS has matched it.
    assert [values[key] for key in MATCHED_KEYS] == ['1', '1', '1']
    late = h.probe.create_subscription(Odometry, 'prediction', lambda msg: None, 10)
    assert spin_until(executor, lambda: h.node.prediction_pub.get_subscription_count() == 2,
                      5.0)
    status, values = h.diagnostics(newer_than=time.time())
    assert [values[key] for key in MATCHED_KEYS] == ['1', '1', '2']
    h.probe.destroy_subscription(late)
    h.probe.destroy_publisher(h.measurement_pub)
    assert spin_until(executor, lambda: h.node.subscription.get_publisher_count() == 0, 5.0)
    status, values = h.diagnostics(newer_than=time.time())
    assert values['measurement_publishers'] == '0'
    h.measurement_pub = h.probe.create_publisher(PoseWithCovarianceStamped, 'measurement', 10)
    assert spin_until(executor, lambda: h.measurement_pub.get_subscription_count() == 1, 5.0)
    assert spin_until(executor, lambda: h.node._timed_out, 5.0)
    status, values = h.diagnostics(newer_than=time.time())
    assert status.level == messages.DIAGNOSTIC_LEVELS['WARN']
    assert 'no measurement fused for' in status.message
    assert float(values['last_measurement_age_s']) > 0.5
    h.send(*_good(11, base))
    assert spin_until(executor, lambda: not h.node._timed_out, 5.0)


def test_reset_service_and_set_state(ros_context, executor):
    """~/reset forgets the state; ~/set_state sets it, or refuses it with a count."""
    h = Harness(ros_context, executor, preset='train', process_noise_density=0.1)
    base = _now_ns() - 60 * NS_PER_S
    for k in range(1, 6):
        h.send(*_good(k, base))
    future = h.reset_client.call_async(Trigger.Request())
    assert spin_until(executor, future.done, 5.0)
    assert future.result().success and 'reset' in future.result().message
    assert not h.node.estimator.initialized
    assert h.node.estimator.stats().resets['manual'] == 1
    h.send(*_good(2, base))  # older than before the reset: it initialises the filter
    assert h.node.estimator.last_stamp_ns == _good(2, base)[0]

    state = messages.to_odometry_msg(_good(3, base)[0], 'odom', 'base_link', 3.0, 10.0,
                                     0.25, 0.5)
    h.set_state_pub.publish(state)
    assert spin_until(executor, lambda: h.node.estimator.stats().resets['set_state'] == 1, 5.0)
    x, P = h.node.estimator.state
    assert np.array_equal(x, [3.0, 10.0]) and np.array_equal(P, np.diag([0.25, 0.5]))
    assert h.node.estimator.last_stamp_ns == _good(3, base)[0]
    expected = StreamEstimator(h.node.estimator.settings)
    expected.set_state(_good(3, base)[0], [3.0, 10.0], np.diag([0.25, 0.5]))
    h.send(*_good(4, base))
    assert np.array_equal(h.node.estimator.state[0], expected.process(*_good(4, base), 1.0).x)

    for bad in (messages.to_odometry_msg(_good(5, base)[0], 'map', 'base_link', 1.0, 1.0,
                                         1.0, 1.0),
                messages.to_odometry_msg(_good(5, base)[0], 'odom', 'base_link', math.nan,
                                         1.0, 1.0, 1.0),
                messages.to_odometry_msg(_good(5, base)[0], 'odom', 'base_link', 1.0, 1.0,
                                         -1.0, 1.0)):
        refused = h.node.set_state_refused
        h.set_state_pub.publish(bad)
        assert spin_until(executor, lambda: h.node.set_state_refused == refused + 1, 5.0)
    assert h.node.estimator.stats().resets['set_state'] == 1
    assert h.node.estimator.last_stamp_ns == _good(4, base)[0]
    # A zero stamp means 'at the newest fused stamp'.
    h.set_state_pub.publish(messages.to_odometry_msg(0, '', 'base_link', 4.0, 10.0, 1.0, 1.0))
    assert spin_until(executor, lambda: h.node.estimator.stats().resets['set_state'] == 2, 5.0)
    assert h.node.estimator.last_stamp_ns == _good(4, base)[0]


def test_runtime_parameter_changes(ros_context, executor):
    """Valid changes apply from the next measurement; invalid ones are refused, old value kept."""
    h = Harness(ros_context, executor, preset='train')
    base = _now_ns() - 60 * NS_PER_S
    for k in range(1, 6):
        h.send(*_good(k, base))
    results = h.set_parameters(measurement_variance=4.0, gate_probability=0.99,
                               history_s=0.5, frame_id='map', diagnostics_period_s=0.2)
    assert all(r.successful for r in results), results
    settings = h.node.estimator.settings
    assert (settings.measurement_variance, settings.gate_probability,
            settings.history_s) == (4.0, 0.99, 0.5)
    twin_prior = h.node.estimator.state
    h.send(*_good(6, base))
    innovation = h.outputs['innovation'][-1]
    P = twin_prior[1]
    expected_S = P[0, 0] + 2 * 0.1 * P[0, 1] + 0.01 * P[1, 1] + 4.0  # H (F P Fᵀ) Hᵀ + R
    assert innovation.vector.y == pytest.approx(expected_S, rel=1e-12)
    assert h.outputs['estimate'][-1].header.frame_id == 'map'
    assert h.node._diagnostics_timer.timer_period_ns == 200_000_000

    before = h.node.estimator.settings
    for values, words in [
            ({'gate_probability': 0.3}, 'gate_probability'),
            ({'initialization': 'bogus'}, 'initialization must be one of'),
            ({'initial_covariance': [1.0, 2.0, 2.0, 1.0]}, 'positive semi-definite'),
            ({'initial_state': [1.0]}, 'initial_state'),
            ({'frame_id': ''}, 'frame_id must not be empty'),
            ({'nis_window': 0}, 'nis_window'),
            ({'max_consecutive_outliers': 0}, 'max_consecutive_outliers'),
            ({'history_s': 'long'}, 'Wrong parameter type'),
            ({'atomically': True, 'measurement_variance': 1.0, 'initialization': 'bogus'},
             'initialization')]:
        results = h.set_parameters(**values)
        assert not all(r.successful for r in results), values
        assert any(words in r.reason for r in results), (values, results)
    assert h.node.estimator.settings == before
    assert h.node.get_parameter('measurement_variance').value == 4.0
    assert h.node.get_parameter('frame_id').value == 'map'
    assert h.node.frame_id == 'map'


def test_clock_jump_resets_the_filter(ros_context, executor):
    """A backwards jump of the simulated node clock resets the filter, unless configured off."""
    h = Harness(ros_context, executor, use_sim_time=True)
    clock = h.node.get_clock()

    def set_clock(seconds):
        h.clock_pub.publish(messages.to_clock_msg(seconds * NS_PER_S))
        assert spin_until(executor, lambda: clock.now().nanoseconds == seconds * NS_PER_S,
                          5.0)

    set_clock(100)
    for k in range(1, 6):
        h.send(100 * NS_PER_S + k * PERIOD_NS - NS_PER_S, float(k))
    set_clock(101)
    h.send(101 * NS_PER_S, 10.0)
    set_clock(50)  # a bag loop
    h.send(50 * NS_PER_S, 10.0)
    assert h.node.estimator.stats().resets['clock_jump'] == 1
    assert h.node.estimator.last_stamp_ns == 50 * NS_PER_S  # it started again from there
    assert h.set_parameters(reset_on_clock_jump=False)[0].successful
    set_clock(20)
    h.send(20 * NS_PER_S + 1, 10.0)
    assert h.node.estimator.stats().resets['clock_jump'] == 1
    assert h.node.estimator.stats().rejections['stale_stamp'] == 1


def test_sim_time_before_the_first_clock_skips_the_future_check(ros_context, executor):
    """With use_sim_time and no /clock yet (time 0), stamps are not judged against it."""
    h = Harness(ros_context, executor, use_sim_time=True)
    h.send(5 * NS_PER_S, 1.0)
    assert h.node.fused == 1


def test_estimate_step_is_backwards_compatible():
    """Build an EstimateStep from its first seven fields (keywords); the new ones default."""
    step = EstimateStep(stamp_ns=1, x=np.zeros(2), P=np.eye(2), update=None,
                        prediction_stamp_ns=2, predicted_x=np.zeros(2), predicted_P=np.eye(2))
    assert (step.measurement_stamp_ns, step.replayed, step.reset) == (0, 0, None)
    with pytest.raises(TypeError):
        EstimateStep(1, np.zeros(2), np.eye(2), None, 2, np.zeros(2), np.eye(2))
    assert issubclass(Rejected, ValueError)
    assert (EstimatorSettings().gate_probability, EstimatorSettings().history_s) == (
        DEFAULT_GATE_PROBABILITY, 0.0)
