"""The rail part of ``kf-train demo`` without DDS: its run, its series, report and figure."""

import re

from kf_train.cli import demo_rail
from kf_train.estimator import EstimatorSettings, NS_PER_S, Rejected, StreamEstimator
from kf_train.ros import messages
from kf_train.sim import make_stream, rail_scenario
import numpy as np
import pytest

SEED = 0


class FakeRailProbe:
    """What the demo's probe records of a rail run, built offline with the core."""

    def __init__(self, rail, settings, start_ns=1_700_000_000 * NS_PER_S):
        """Stream the simulator's samples, run the estimator on them as the node does."""
        self.received = {topic: [] for topic in ('measurement', 'ground_truth',
                                                 'ground_truth_accel', 'estimate',
                                                 'prediction', 'regime_probabilities')}
        stream = make_stream('rail', demo_rail.RATE_HZ, rail.seed,
                             rail={'family': demo_rail.FAMILY})
        estimator = StreamEstimator(settings)
        for _ in range(rail.samples):
            sample = stream.next_sample()
            stamp_ns = start_ns + sample.index * NS_PER_S // 10
            self.add('measurement', messages.to_measurement_msg(
                stamp_ns, 'odom', sample.measured_position_m, 1.0))
            self.add('ground_truth', messages.to_odometry_msg(
                stamp_ns, 'odom', 'base_link', sample.true_position_m,
                sample.true_velocity_mps, 0.0, 0.0))
            self.add('ground_truth_accel', messages.to_accel_msg(
                stamp_ns, 'base_link', sample.true_acceleration_mps2))
            try:
                step = estimator.process(stamp_ns, sample.measured_position_m, 1.0)
            except Rejected:
                continue
            self.add('estimate', messages.to_estimate_msg(stamp_ns, 'odom', 'base_link',
                                                          step.x[:2], step.P[:2, :2]))
            self.add('prediction', messages.to_estimate_msg(
                step.prediction_stamp_ns, 'odom', 'base_link', step.predicted_x[:2],
                step.predicted_P[:2, :2]))
            regimes = estimator.mode_probabilities()
            if regimes is not None:
                self.add('regime_probabilities', messages.to_regime_msg(*regimes))

    def add(self, topic, msg):
        """Record one message."""
        self.received[topic].append(msg)


@pytest.fixture(scope='module')
def rail():
    """Return the demo's run of seed 0."""
    return demo_rail.plan(SEED)


def test_the_demo_run_reaches_a_station_and_is_rail_scenario(rail):
    """The run goes through a departure and a stop; its samples are the seeded scenario's."""
    arrival, departure = rail.stop
    assert 30.0 < arrival < rail.samples / demo_rail.RATE_HZ <= demo_rail.MAX_DURATION_S
    assert rail.samples / demo_rail.RATE_HZ >= min(arrival + demo_rail.AFTER_ARRIVAL_S,
                                                   demo_rail.MAX_DURATION_S)
    full, _ = rail_scenario(SEED, demo_rail.FAMILY)
    np.testing.assert_array_equal(rail.scenario.z, full.z[:rail.samples])
    np.testing.assert_array_equal(rail.scenario.truth, full.truth[:rail.samples])
    states = rail.run.state_at(rail.scenario.t_s)
    assert states.velocity_mps.max() > 10.0 and states.velocity_mps[-1] == 0.0


@pytest.mark.parametrize('preset', ['rail', 'train'])
def test_the_rail_series_report_and_figure(rail, tmp_path, preset):
    """Offline core = 'DDS', the truth = the seeded run, the scores are rail_eval's."""
    settings = EstimatorSettings(preset=preset, gate_probability=0.9999)
    probe = FakeRailProbe(rail, settings)
    series = demo_rail.build_rail_series(probe, rail, settings)
    assert series.offline_max_abs_diff == 0.0 and series.simulation_max_abs_diff == 0.0
    assert len(series.estimate_t_s) == rail.samples - series.rejected
    assert series.regime_names == (('stand', 'accelerate', 'cruise', 'brake')
                                   if preset == 'rail' else ())
    tuned = demo_rail.tuned_baselines(rail.scenario, rail.run, cv_grid=(1.0, 3.0),
                                      ca_grid=(0.03, 0.1))
    figure = demo_rail._draw(tmp_path, rail, series)
    assert figure and (tmp_path / 'rail.png').stat().st_size > 10_000
    report = demo_rail.format_rail_report(rail, series, settings, tuned, 7, figure)
    ours = demo_rail.score_predictions(demo_rail.dds_track(series), rail.run)
    line = next(line for line in report.splitlines() if 'estimator defaults' in line)
    assert f'{ours.rmse_m:.3f}' in line and f'{100 * ours.coverage:.1f} %' in line
    for name in ('CV', 'CA'):
        assert f'{tuned[name].score.rmse_m:.3f}' in report
    ratio = float(re.search(r'best tuned KF: (\S+)', report)[1])
    best = min(t.score.rmse_m for t in tuned.values())
    assert ratio == pytest.approx(ours.rmse_m / best, abs=0.006)
    assert f'preset {preset}' in report and 'max |difference| = 0\n' in report
    if preset == 'rail':
        # The rail IMM on its demo run: better than both tuned KFs, an honest band.
        assert ratio < 1.0 and 0.85 <= ours.coverage <= 0.99
