"""
Integration tests: the simulator, the estimator and a probe node on one executor.

Every test has its own Context and ROS domain (fixtures in conftest.py); all waits
are bounded. Statistical bounds come from a stated false-alarm probability.
"""

import math
import os
import statistics

from geometry_msgs.msg import PoseWithCovarianceStamped
from kf_train.cli.demo_processes import settings_from_parameters
from kf_train.estimator import EstimatorSettings, NS_PER_S, SEED_SWITCH, StreamEstimator
from kf_train.ros import messages
from kf_train.ros.demo_nodes import Probe
from kf_train.ros.estimator_node import EstimatorNode
from kf_train.ros.simulator_node import SimulatorNode
import numpy as np
import pytest
from rcl_interfaces.msg import ParameterType
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import spin_until
from rosgraph_msgs.msg import Clock
import yaml

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CONFIG = os.path.join(REPO, 'config', 'kf_train.yaml')
TIMEOUT_S = 30.0
FALSE_ALARM = 1e-6
"""Probability that a correct filter fails a test's k·σ checks, all of them together."""
IMPLICIT_PARAMETERS = {'use_sim_time', 'start_type_description_service'}


def k_sigma(checks: int, false_alarm: float = FALSE_ALARM) -> float:
    """Return k with P(|N(0, 1)| > k) = false_alarm / checks (Bonferroni over the checks)."""
    return statistics.NormalDist().inv_cdf(1.0 - false_alarm / checks / 2.0)


def start(executor, context, simulator=None, estimator=None, probe=True):
    """Create the nodes whose parameter dicts are given, add them to ``executor``."""
    nodes = []
    if simulator is not None:
        nodes.append(SimulatorNode(context=context, parameter_overrides=[
            Parameter(name, value=value) for name, value in simulator.items()]))
    if estimator is not None:
        nodes.append(EstimatorNode(context=context, parameter_overrides=[
            Parameter(name, value=value) for name, value in estimator.items()]))
    if probe:
        nodes.append(Probe(context=context))
    for node in nodes:
        executor.add_node(node)
    return nodes


ALL_TOPICS = ('measurement', 'ground_truth', 'estimate', 'prediction')


def wait_for(executor, probe, samples, topics=ALL_TOPICS):
    """Spin until every topic in ``topics`` has delivered ``samples`` messages."""
    assert spin_until(executor, lambda: all(len(probe.received[t]) >= samples
                                            for t in topics), TIMEOUT_S), probe.counts()


def by_stamp(msgs):
    """Return {stamp_ns: message}, checking that no stamp repeats."""
    table = {messages.stamp_to_ns(m.header.stamp): m for m in msgs}
    assert len(table) == len(msgs), 'repeated stamps'
    return table


def states(probe, topic):
    """Return the OdometryStates of ``topic`` sorted by stamp."""
    return sorted(map(messages.from_odometry_msg, probe.received[topic]),
                  key=lambda s: s.stamp_ns)


def measurements(probe):
    """Return the measurements the probe saw, sorted by stamp."""
    return sorted(map(messages.from_measurement_msg, probe.received['measurement']),
                  key=lambda m: m.stamp_ns)


def seed_000_matlab(Z_samples, dt=0.1, ahead_samples=20):
    """
    Run a literal transcription of seed 000's Kalman loop; return Xk, P and projections.

    The projection is the seed's ``Xk(1) + SamplesIntoTheFuture·dt·Xk(2)``; its
    variance is [1, h]·P·[1, h]' with h = SamplesIntoTheFuture·dt.
    """
    Xk_prev = np.array([[0.0], [0.5 * 10.0]])   # Xk_prev = [0; .5*Vtrue]
    Phi = np.array([[1.0, dt], [0.0, 1.0]])     # Phi = [1 dt; 0 1]
    sigma_model = 1.0
    P = np.array([[sigma_model ** 2, 0.0], [0.0, sigma_model ** 2]])
    Q = np.zeros((2, 2))                        # Q = [0 0; 0 0]
    M = np.array([[1.0, 0.0]])                  # M = [1 0]
    sigma_meas = 1.0
    R = sigma_meas ** 2
    Xk_buffer, P_buffer, projected, projected_var = [], [], [], []
    h = ahead_samples * dt
    for Z in Z_samples:
        P1 = Phi @ P @ Phi.T + Q                # P1 = Phi*P*Phi' + Q
        S = M @ P1 @ M.T + R                    # S = M*P1*M' + R
        K = P1 @ M.T @ np.linalg.inv(S)         # K = P1*M'*inv(S)
        P = P1 - K @ M @ P1                     # P = P1 - K*M*P1
        Xk = Phi @ Xk_prev + K @ (Z - M @ Phi @ Xk_prev)
        Xk_buffer.append(Xk.ravel())
        P_buffer.append(P)
        projected.append(Xk[0, 0] + h * Xk[1, 0])
        projected_var.append((np.array([1.0, h]) @ P @ np.array([1.0, h])))
        Xk_prev = Xk                            # Xk_prev = Xk
    return (np.array(Xk_buffer), np.array(P_buffer), np.array(projected),
            np.array(projected_var))


def test_prior_mode_over_dds_is_seed_000_and_converges(ros_context, executor):
    """
    Seed 000 at 10 Hz: the node reproduces the MATLAB loop to 1e-9 and converges.

    Also: estimates carry their measurement's stamp, predictions that stamp + 2 s
    exactly, and σ never grows (Q = 0).
    """
    samples = 100
    _, _, probe = start(executor, ros_context,
                        simulator={'max_samples': samples, 'min_subscribers': 2},
                        estimator=dict(SEED_SWITCH))
    wait_for(executor, probe, samples)
    z = measurements(probe)
    stamps = [m.stamp_ns for m in z]
    assert np.all(np.diff(stamps) == NS_PER_S // 10)  # 10 Hz, exact in integer ns
    assert all(m.variance_m2 == 1.0 for m in z)
    est = states(probe, 'estimate')
    pred = states(probe, 'prediction')
    assert [s.stamp_ns for s in est] == stamps
    assert [s.stamp_ns for s in pred] == [s + 2 * NS_PER_S for s in stamps]

    Xk, P, projected, projected_var = seed_000_matlab([m.position_m for m in z])
    np.testing.assert_allclose([[s.position_m, s.velocity_mps] for s in est], Xk,
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose([[s.position_variance_m2, s.velocity_variance_m2s2]
                                for s in est], P[:, [0, 1], [0, 1]], rtol=0, atol=1e-9)
    np.testing.assert_allclose([s.position_m for s in pred], projected, rtol=0, atol=1e-9)
    np.testing.assert_allclose([s.position_variance_m2 for s in pred], projected_var,
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose([s.velocity_mps for s in pred], Xk[:, 1], rtol=0, atol=1e-9)

    truth = by_stamp(probe.received['ground_truth'])
    last = est[-1]
    true_last = messages.from_odometry_msg(truth[last.stamp_ns])
    k = k_sigma(checks=2)
    # The seed's prior (v0 = 5 ± 1 m/s, truth 10) weighs ~1/800 of the data at the
    # end, biasing by ~0.2σ: far inside k ≈ 5.
    assert abs(last.position_m - true_last.position_m) <= k * math.sqrt(
        last.position_variance_m2)
    assert abs(last.velocity_mps - true_last.velocity_mps) <= k * math.sqrt(
        last.velocity_variance_m2s2)
    sigma = np.sqrt([[s.position_variance_m2, s.velocity_variance_m2s2] for s in est])
    assert np.all(np.diff(sigma, axis=0) <= 1e-15), 'σ grew although Q = 0'
    assert np.all(sigma[-1] < 0.5 * sigma[0])


@pytest.mark.parametrize('horizon_s', [0.75, 1.0 / 3.0])
def test_every_message_is_fully_filled(ros_context, executor, horizon_s):
    """Stamps, frames, orientation, covariance layout, finiteness; predictions at +horizon."""
    samples = 20
    frames = {'frame_id': 'map', 'child_frame_id': 'train_base'}
    _, _, probe = start(executor, ros_context,
                        simulator=dict(frames, rate_hz=100.0, max_samples=samples,
                                       min_subscribers=2),
                        estimator={'frame_id': 'map', 'child_frame_id': 'train_est',
                                   'horizon_s': horizon_s})
    wait_for(executor, probe, samples)
    horizon_ns = round(horizon_s * NS_PER_S)
    meas = by_stamp(probe.received['measurement'])
    truth = by_stamp(probe.received['ground_truth'])
    assert sorted(meas) == sorted(truth), 'measurement and ground truth stamps differ'
    assert sorted(by_stamp(probe.received['estimate'])) == sorted(meas)
    assert sorted(by_stamp(probe.received['prediction'])) == [s + horizon_ns
                                                              for s in sorted(meas)]

    for msg in probe.received['measurement']:
        assert messages.stamp_to_ns(msg.header.stamp) > 0
        assert msg.header.frame_id == 'map'
        check_pose(msg.pose, first_variance=1.0)
    for topic, child, velocity_variance in (('ground_truth', 'train_base', 0.0),
                                            ('estimate', 'train_est', None),
                                            ('prediction', 'train_est', None)):
        for msg in probe.received[topic]:
            assert messages.stamp_to_ns(msg.header.stamp) > 0
            assert (msg.header.frame_id, msg.child_frame_id) == ('map', child)
            check_pose(msg.pose, first_variance=0.0 if topic == 'ground_truth' else None)
            twist = msg.twist.twist
            assert math.isfinite(twist.linear.x)
            assert (twist.linear.y, twist.linear.z) == (0.0, 0.0)
            assert (twist.angular.x, twist.angular.y, twist.angular.z) == (0.0, 0.0, 0.0)
            check_covariance(msg.twist.covariance, velocity_variance)
    for msg in probe.received['ground_truth']:
        assert msg.twist.twist.linear.x == 10.0


def check_pose(pose_with_covariance, first_variance=None):
    """Check a 1-D pose: finite x, y = z = 0, identity orientation, documented covariance."""
    pose = pose_with_covariance.pose
    assert math.isfinite(pose.position.x)
    assert (pose.position.y, pose.position.z) == (0.0, 0.0)
    q = pose.orientation
    assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 1.0)
    check_covariance(pose_with_covariance.covariance, first_variance)


def check_covariance(covariance, first_variance=None):
    """Check messages.py's layout: [0] the variance, other diagonal UNESTIMATED, else 0."""
    c = np.asarray(covariance, dtype=float).reshape(6, 6)
    assert np.all(np.isfinite(c))
    if first_variance is None:
        assert c[0, 0] > 0.0
    else:
        assert c[0, 0] == first_variance
    assert np.all(np.diag(c)[1:] == messages.UNESTIMATED_VARIANCE)
    assert np.all(c[~np.eye(6, dtype=bool)] == 0.0)


def test_first_measurement_mode_converges_far_down_the_track(ros_context, executor):
    """Joining a train at 6 km: within noise from the first sample, consistent throughout."""
    samples = 40
    _, _, probe = start(executor, ros_context,
                        simulator={'initial_position': 6000.0, 'rate_hz': 20.0,
                                   'max_samples': samples, 'min_subscribers': 2},
                        estimator={'preset': 'train', 'gate_probability': 1.0})
    wait_for(executor, probe, samples, topics=('ground_truth', 'estimate'))
    truth = by_stamp(probe.received['ground_truth'])
    est = states(probe, 'estimate')
    assert messages.from_odometry_msg(truth[est[0].stamp_ns]).position_m > 6000.0
    k = k_sigma(checks=2 * samples)
    for s in est:
        true = messages.from_odometry_msg(truth[s.stamp_ns])
        assert abs(s.position_m - true.position_m) <= k * math.sqrt(s.position_variance_m2)
        assert abs(s.velocity_mps - true.velocity_mps) <= k * math.sqrt(
            s.velocity_variance_m2s2)
        assert s.position_variance_m2 <= 1.0 + 1e-12  # never worse than one measurement
    # Least squares of a line through n points: var(v) = 12 R / (n (n² - 1) dt²).
    n, dt = samples, 1.0 / 20.0
    assert est[-1].velocity_variance_m2s2 <= 1.01 * 12.0 / (n * (n * n - 1) * dt * dt)
    # The seed's prior on the same data would be hopelessly off: the scenario matters.
    prior = StreamEstimator(EstimatorSettings(**SEED_SWITCH, nominal_period_s=dt))
    for m in measurements(probe):
        step = prior.process(m.stamp_ns, m.position_m, m.variance_m2)
    assert abs(step.x[0] - est[-1].position_m) > 100.0 * math.sqrt(step.P[0, 0])


@pytest.mark.parametrize('reliability', [ReliabilityPolicy.RELIABLE,
                                         ReliabilityPolicy.BEST_EFFORT])
def test_estimator_takes_reliable_and_best_effort_publishers(
        ros_context, executor, reliability):
    """A publisher of either reliability (depth 10) is matched and every message fused."""
    estimator, probe = start(executor, ros_context, estimator={})
    publisher = probe.create_publisher(PoseWithCovarianceStamped, 'measurement',
                                       QoSProfile(depth=10, reliability=reliability))
    assert spin_until(executor, lambda: publisher.get_subscription_count() >= 1, TIMEOUT_S)
    offline = StreamEstimator(settings_from_parameters(declared(estimator)))
    start_ns = 1_700_000_000 * NS_PER_S
    for k in range(1, 11):
        stamp_ns = start_ns + k * 50_000_000
        position_m = 3.0 * k + (-1.0) ** k * 0.25
        publisher.publish(messages.to_measurement_msg(stamp_ns, 'odom', position_m, 0.25))
        assert spin_until(executor, lambda: len(probe.received['estimate']) >= k,
                          TIMEOUT_S)
        step = offline.process(stamp_ns, position_m, 0.25)
        got = messages.from_odometry_msg(probe.received['estimate'][-1])
        assert got.stamp_ns == stamp_ns
        # The defaults: the rail IMM; the Odometry carries its position and velocity.
        assert [got.position_m, got.velocity_mps] == step.x.tolist()[:2]
        assert [got.position_variance_m2, got.velocity_variance_m2s2] == \
            np.diag(step.P).tolist()[:2]


def publish_measurement(executor, probe, publisher, stamp_ns, position_m=0.0, variance=1.0):
    """Publish one measurement and spin until its prediction arrives; return it."""
    before = len(probe.received['prediction'])
    publisher.publish(messages.to_measurement_msg(stamp_ns, 'odom', position_m, variance))
    assert spin_until(executor, lambda: len(probe.received['prediction']) > before,
                      TIMEOUT_S)
    return messages.from_odometry_msg(probe.received['prediction'][-1])


def test_runtime_parameter_changes_through_the_node(ros_context, executor):
    """Valid changes are accepted and applied; invalid ones refused with a reason."""
    # The simulator never starts (it waits for 1000 subscribers): the test publishes.
    simulator, estimator, probe = start(
        executor, ros_context, simulator={'rate_hz': 100.0, 'min_subscribers': 1000},
        estimator={})
    publisher = probe.create_publisher(PoseWithCovarianceStamped,
                                       'measurement', 10)
    assert spin_until(executor, lambda: publisher.get_subscription_count() >= 1, TIMEOUT_S)

    [result] = estimator.set_parameters([Parameter('horizon_s', value=0.5)])
    assert result.successful, result.reason
    assert estimator.get_parameter('horizon_s').value == 0.5
    prediction = publish_measurement(executor, probe, publisher, 10 * NS_PER_S)
    assert prediction.stamp_ns == 10 * NS_PER_S + NS_PER_S // 2  # applied

    refused = [
        (Parameter('horizon_s', value=-1.0), 'horizon_s'),
        (Parameter('horizon_s', value=3), 'type'),
        (Parameter('initial_covariance', value=[1.0, -1.0]), 'initial_covariance'),
        (Parameter('initialization', value='bogus'), 'initialization'),
        (Parameter('frame_id', value=''), 'frame_id'),
    ]
    for parameter, named in refused:
        old = estimator.get_parameter(parameter.name).value
        [result] = estimator.set_parameters([parameter])
        assert not result.successful, parameter.name
        assert named in result.reason
        assert estimator.get_parameter(parameter.name).value == old
    prediction = publish_measurement(executor, probe, publisher, 11 * NS_PER_S)
    assert prediction.stamp_ns == 11 * NS_PER_S + NS_PER_S // 2  # still 0.5 s
    assert prediction.frame_id == 'odom'

    [result] = simulator.set_parameters([Parameter('noise_std', value=0.5)])
    assert result.successful and simulator.simulation.noise_std_m == 0.5
    [result] = simulator.set_parameters([Parameter('rate_hz', value=20.0)])
    assert not result.successful and 'rate_hz' in result.reason
    assert simulator.get_parameter('rate_hz').value == 100.0


def test_runtime_parameter_changes_through_the_service(ros_context, executor):
    """``ros2 param set`` equivalent: the SetParameters service accepts and refuses."""
    _, probe = start(executor, ros_context, estimator={})
    client = AsyncParameterClient(probe, 'estimator')
    assert client.wait_for_services(timeout_sec=TIMEOUT_S)

    def call(future):
        assert spin_until(executor, future.done, TIMEOUT_S)
        return future.result()

    ok = call(client.set_parameters([Parameter('horizon_s', value=1.5)])).results[0]
    assert ok.successful, ok.reason
    bad = call(client.set_parameters([Parameter('horizon_s', value=-3.0)])).results[0]
    assert not bad.successful and 'horizon_s' in bad.reason
    bad = call(client.set_parameters(
        [Parameter('process_noise_density', value='high')])).results[0]
    assert not bad.successful and bad.reason
    [value] = call(client.get_parameters(['horizon_s'])).values
    assert (value.type, value.double_value) == (ParameterType.PARAMETER_DOUBLE, 1.5)


def test_simulator_stamps_follow_sim_time(ros_context, executor):
    """With use_sim_time the samples are stamped and timed by /clock, not the wall clock."""
    simulator, probe = start(executor, ros_context,
                             simulator={'use_sim_time': True, 'rate_hz': 10.0})
    clock = probe.create_publisher(Clock, '/clock', 10)
    assert spin_until(executor, lambda: clock.get_subscription_count() >= 1, TIMEOUT_S)
    t0_ns = 1000 * NS_PER_S
    published = []
    # The timer was armed at sim time 0, so the jump to t0 fires it; each further
    # step of one period fires it once more.
    for step in range(5):
        now_ns = t0_ns + step * (NS_PER_S // 10)
        clock.publish(Clock(clock=messages.ns_to_stamp(now_ns)))
        published.append(now_ns)
        assert spin_until(executor, lambda: (
            simulator.get_clock().now().nanoseconds == now_ns
            and simulator.published == step + 1
            and len(probe.received['measurement']) == step + 1), TIMEOUT_S), step
    assert sorted(by_stamp(probe.received['measurement'])) == published


def load_config():
    """Return the parameters config/kf_train.yaml gives each node."""
    with open(CONFIG) as stream:
        config = yaml.safe_load(stream)
    return {node: entry['ros__parameters'] for node, entry in config.items()}


def declared(node):
    """Return {name: value} of everything ``node`` declared itself."""
    return {name: parameter.value
            for name, parameter in node.get_parameters_by_prefix('').items()
            if name not in IMPLICIT_PARAMETERS and not name.startswith('qos_overrides.')}


def same(a, b):
    """Return whether two parameter values are equal in value and type."""
    if isinstance(a, (list, tuple)) or hasattr(a, 'typecode'):
        return (isinstance(b, (list, tuple)) or hasattr(b, 'typecode')) and \
            len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and a == b


def test_config_file_lists_exactly_the_declared_defaults(ros_context):
    """config/kf_train.yaml names every declared parameter, with its declared default."""
    config = load_config()
    assert set(config) == {'simulator', 'estimator'}
    for node in (SimulatorNode(context=ros_context), EstimatorNode(context=ros_context)):
        defaults = declared(node)
        listed = config[node.get_name()]
        assert set(listed) == set(defaults), node.get_name()
        for name, value in defaults.items():
            assert same(listed[name], value), (node.get_name(), name, listed[name], value)


@pytest.mark.parametrize('changed', [False, True])
def test_nodes_start_from_the_params_file(domain_id, tmp_path, changed):
    """``--ros-args --params-file`` reaches both nodes: the shipped file and an edited one."""
    config = load_config()
    path = CONFIG
    if changed:
        config['simulator'].update(rate_hz=20.0, seed=7, frame_id='map')
        config['estimator'].update(horizon_s=1.5, initialization='prior',
                                   initial_state=[1.0, 2.0, 0.0, 0.0, 0.8, 0.9])
        path = str(tmp_path / 'changed.yaml')
        with open(path, 'w') as stream:
            yaml.safe_dump({node: {'ros__parameters': values}
                            for node, values in config.items()}, stream)
    context = Context()
    rclpy.init(args=['--ros-args', '--params-file', path], context=context,
               domain_id=domain_id)
    try:
        for node in (SimulatorNode(context=context), EstimatorNode(context=context)):
            values = declared(node)
            for name, value in config[node.get_name()].items():
                assert same(values[name], value), (node.get_name(), name)
            node.destroy_node()
    finally:
        context.try_shutdown()
