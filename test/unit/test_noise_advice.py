"""
The suggested q in the estimator's /diagnostics, without ROS: a session fed measurements.

:class:`kf_train.ros.session.EstimatorSession` is what the node runs on every message
(and ``kf-train replay BAG`` too); its :meth:`diagnostics` builds the status with
:func:`kf_train.ros.diagnostics.with_noise_suggestion`.
"""

from kf_train.ros import noise_advice
from kf_train.ros.diagnostics import FilterStatus, with_noise_suggestion
from kf_train.ros.estimator_params import load_estimator_config
from kf_train.ros.session import EstimatorSession, Measurement
from kf_train.sim import car_scenario, white_noise_acceleration_scenario
import pytest

NS = 1_000_000_000
EPOCH_NS = 1_700_000_000 * NS
KEYS = ['suggested_process_noise_density', 'suggested_process_noise_density_low_95',
        'suggested_process_noise_density_high_95', 'suggested_process_noise_window',
        'suggested_process_noise_window_s', 'process_noise_advice']


class Clock:
    """The record time of the message being fed, as the session's steady clock."""

    def __init__(self):
        """Start at the epoch."""
        self.now_ns = EPOCH_NS

    def seconds(self) -> float:
        """Return the time [s]."""
        return self.now_ns / NS


def session_fed(q_true, rows, *overrides, seed=3, scenario=None):
    """
    Return (session, clock) after ``rows`` measurements of a random-force train at 10 Hz.

    Preset train, gate off, unless ``overrides`` say otherwise.
    """
    clock = Clock()
    # The train's KF without a gate (the node's defaults before issue 11 made them the
    # rail IMM with the gate on): the suggested q is the constant-velocity model's.
    session = EstimatorSession(load_estimator_config(
        [], ['preset:=train', 'gate_probability:=1.0'] + list(overrides)), clock.seconds)
    scenario = scenario or white_noise_acceleration_scenario(q_true, 1.0, rows, seed=seed)
    for k, (t, z) in enumerate(zip(scenario.t_s.tolist(), scenario.z[:, 0].tolist())):
        clock.now_ns = stamp_ns = EPOCH_NS + round(t * NS)
        if scenario.u is not None:
            session.on_control(_Control(stamp_ns, float(scenario.u[k, 0])), stamp_ns)
        session.on_measurement(Measurement(stamp_ns, 'odom', z, 1.0), stamp_ns)
    return session, clock


class _Control:
    """A control message as the session takes it."""

    def __init__(self, stamp_ns, value):
        """Hold the stamp and the value."""
        self.stamp_ns, self.value = stamp_ns, value


def test_too_little_noise_is_told_to_increase_q():
    """Node q = 0, train under random force (q = 2): WARN too small, 'increase q', how far."""
    session, clock = session_fed(2.0, 300)
    status = session.diagnostics(clock.now_ns)
    values = dict(status.values)
    assert [key for key, _ in status.values][-len(KEYS):] == KEYS
    assert status.level == 'WARN'
    assert 'noise parameters too small' in status.message
    assert status.message.endswith(values['process_noise_advice'])
    assert values['process_noise_advice'].startswith('increase q: suggested ')
    low = float(values['suggested_process_noise_density_low_95'])
    high = float(values['suggested_process_noise_density_high_95'])
    q = float(values['suggested_process_noise_density'])
    assert 0.0 < low <= 2.0 <= high and low <= q <= high
    assert values['suggested_process_noise_window'] == '299'      # innovations of 300 rows
    assert values['suggested_process_noise_window_s'] == '29.900'


def test_too_much_noise_is_told_to_decrease_q_and_a_reset_empties_the_window():
    """Node q = 200, train at constant speed: the NIS window sees nothing, the advice does."""
    session, clock = session_fed(0.0, 200, 'process_noise_density:=200.0')
    status = session.diagnostics(clock.now_ns)
    values = dict(status.values)
    # A filter with far too much q follows the measurements: its innovations are
    # about as large as it predicts, and the mean NIS stays in its bounds.
    assert status.level == 'OK'
    assert values['process_noise_advice'].startswith('decrease q')
    assert values['suggested_process_noise_density_low_95'] == '0'
    assert float(values['suggested_process_noise_density_high_95']) < 200.0
    assert status.message == 'ok; ' + values['process_noise_advice']
    session.reset()
    assert 'suggested_process_noise_density' not in dict(session.diagnostics(clock.now_ns)
                                                         .values)


def test_an_r_too_large_with_q_consistent_points_at_r():
    """R = 25 on R = 1 data: NIS too large, q consistent: the message says check R."""
    session, clock = session_fed(0.0, 200, 'measurement_variance:=25.0')
    status = session.diagnostics(clock.now_ns)
    assert 'noise parameters too large' in status.message
    assert status.message.endswith(': check the measurement variance R')
    assert 'q = 0 is consistent' in status.message


def test_keys_only_when_meaningful():
    """Before 30 measurements, with the window off, and for the robot (no q): no keys."""
    session, clock = session_fed(2.0, 30)        # 30 measurements: the first suggestion
    assert 'suggested_process_noise_density' in dict(session.diagnostics(clock.now_ns).values)
    session, clock = session_fed(2.0, 29)
    assert 'suggested_process_noise_density' not in dict(
        session.diagnostics(clock.now_ns).values)
    session, clock = session_fed(2.0, 100, 'noise_suggestion_window:=0')
    assert session.noise.unavailable == 'noise_suggestion_window is 0'
    assert not set(KEYS) & set(dict(session.diagnostics(clock.now_ns).values))
    robot = EstimatorSession(load_estimator_config([], ['preset:=robot']), lambda: 0.0)
    assert not robot.noise.active and 'no white-noise acceleration' in robot.noise.unavailable


def test_a_consistent_q_is_said_so_and_the_message_stays_ok():
    """The right q: OK, message 'ok', the advice says q is consistent."""
    session, clock = session_fed(0.5, 300, 'process_noise_density:=0.5', seed=8)
    status = session.diagnostics(clock.now_ns)
    assert (status.level, status.message) == ('OK', 'ok')
    assert dict(status.values)['process_noise_advice'].startswith('q = 0.5 is consistent')


def test_the_suggestion_is_recomputed_once_per_window_and_on_new_noise():
    """Between refreshes the diagnostics reuse the suggestion: cheap per period."""
    session, clock = session_fed(2.0, 120, 'noise_suggestion_window:=60')
    advisor = session.noise
    assert advisor.window == 60 and advisor.refresh_every == 60
    first = advisor.suggestion(session._node_variances)
    count = advisor._estimate.evaluations
    assert advisor.suggestion(session._node_variances) is first
    assert advisor._estimate.evaluations == count
    session.apply_changes({'process_noise_density': 1.0})      # q: the same suggestion
    assert advisor.suggestion(session._node_variances) is first
    session.apply_changes({'measurement_variance': 4.0})       # R changed: recompute
    second = advisor.suggestion(session._node_variances)
    # with R = 4 on R = 1 data the window wants less q
    assert second.process_noise_density < first.process_noise_density
    # a live change of the window starts a new, empty one
    session.apply_changes({'noise_suggestion_window': 100})
    assert session.noise is not advisor and session.noise.suggestion() is None


def test_a_control_preset_and_an_out_of_sequence_measurement():
    """car-exact (controls): its own noise fits, q ~ 0 suggested; a late one is left out."""
    preset_run = car_scenario(seed=4, n_samples=200, exact=True)
    session, clock = session_fed(None, 200, 'preset:=car-exact', scenario=preset_run)
    values = dict(session.diagnostics(clock.now_ns).values)
    assert values['suggested_process_noise_density_low_95'] == '0'
    assert values['process_noise_advice'].startswith('q = 0 is consistent')
    rows = len(session.noise._estimate)
    late = clock.now_ns - NS // 20                 # 50 ms old: fused out of sequence
    session.on_measurement(Measurement(late, 'odom', 0.0, 1.0), clock.now_ns)
    assert len(session.noise._estimate) == rows


def test_the_builder_leaves_a_status_without_suggestion_alone():
    """No suggestion: the very status object; one: the keys appended, the level kept."""
    status = FilterStatus('OK', 'ok', [('preset', 'train')], None)
    assert with_noise_suggestion(status, None, 0.0, 0.0) is status
    suggestion = noise_advice.NoiseSuggestion(2.0, 1.0, 4.0, 99)
    built = with_noise_suggestion(status, suggestion, 0.1, 9.9)
    advice = dict(built.values)['process_noise_advice']
    assert advice.startswith('increase q about x20')
    assert built.level == 'OK' and built.message == 'ok; ' + advice
    inside = with_noise_suggestion(status, suggestion, 3.0, 9.9)
    assert inside.message == 'ok' and built.values[0] == ('preset', 'train')


@pytest.mark.parametrize('window, expected', [(5, 10), (300, 300), (3000, 3000)])
def test_small_windows_count_as_ten(window, expected):
    """A window below MIN_WINDOW is MIN_WINDOW."""
    from kf_train.presets import load_preset
    assert noise_advice.NoiseAdvisor(load_preset('train'), window).window == expected


def test_a_window_the_likelihood_refuses_gives_no_suggestion_until_the_next_refresh():
    """R = 0 for the window (impossible for the node, forced here): no keys, no exception."""
    session, clock = session_fed(2.0, 60)
    advisor = session.noise
    assert advisor.suggestion(lambda raw: (0.0,)) is None
    evaluations = advisor._estimate.evaluations
    assert advisor.suggestion(lambda raw: (0.0,)) is None      # not retried at once
    assert advisor._estimate.evaluations == evaluations
    for k in range(1, advisor.refresh_every + 1):
        stamp_ns = clock.now_ns + k * NS // 10
        session.on_measurement(Measurement(stamp_ns, 'odom', 0.0, 1.0), stamp_ns)
    assert advisor.suggestion(session._node_variances) is not None


def test_the_advisor_reads_the_estimators_r():
    """The window's R is the estimator's (measurement_noise), the one override rule."""
    session, _ = session_fed(2.0, 10, 'measurement_variance:=4.0')
    estimator = session.estimator
    assert session._node_variances((1.0,)) == (4.0,) == tuple(
        estimator.measurement_noise(1.0).diagonal().tolist())
    session.apply_changes({'measurement_variance': 0.0})       # the message's again
    assert session._node_variances((2.5,)) == (2.5,)
    velocity = EstimatorSession(load_estimator_config(
        [], ['preset:=cv-position-velocity', 'measurement_velocity_variance:=9.0']), float)
    assert velocity._node_variances((1.0, 0.5)) == (1.0, 9.0)
    assert velocity.estimator.measurement_noise(1.0, 0.5).tolist() == [[1.0, 0.0], [0.0, 9.0]]
