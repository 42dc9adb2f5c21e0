"""Tests of the model contract (kf_train.filters.contract) and of who implements it."""

from kf_train.estimator import (
    EstimateStep, EstimatorSettings, LIVE_PRESETS, NS_PER_S, RAIL_FILTER_KINDS, StreamEstimator)
from kf_train.estimator.imm_model import IMMModel
from kf_train.filters import (
    first_jump_row, IMM, IMMFilter, make_filter, PredictThenUpdate, RailModel, RateTransition,
    StepModel)
from kf_train.presets import load_preset
import numpy as np
import pytest

KINDS = ('kf', 'ekf', 'ukf', 'pf', 'bootstrap-pf')


def _settings(preset: str, kind: str) -> EstimatorSettings:
    """Return settings of ``preset`` run as ``kind`` (no gate; few particles)."""
    return EstimatorSettings(preset=preset, filter=kind, gate_probability=1.0,
                             pf_particles=50, initialization='prior')


def _every_estimator_model():
    """Yield (preset, kind, fast, model) for every model a StreamEstimator can run."""
    for preset in LIVE_PRESETS:
        for kind in (RAIL_FILTER_KINDS if preset == 'rail' else KINDS):
            for fast in (True, False):
                estimator = object.__new__(StreamEstimator)
                estimator.fast_path = fast
                StreamEstimator.__init__(estimator, _settings(preset, kind))
                yield preset, kind, fast, estimator.model


def test_every_preset_model_satisfies_the_contract():
    """The KF, fast train KF, EKF, UKF, both PFs and the rail IMM: all StepModels."""
    seen = set()
    for preset, kind, fast, model in _every_estimator_model():
        assert isinstance(model, StepModel), (preset, kind, fast, type(model))
        assert model.dim_x == len(model.state_names)
        assert model.dim_z == len(model.measurement_names)
        assert isinstance(model.control_names, tuple)
        seen.add(type(model).__name__)
    assert {'_FastTrainModel', '_CachedModel', 'LinearModel', 'UnscentedModel',
            '_ParticleModel', 'IMMModel'} <= seen
    # The filter family's own pure models too (the range-bearing EKF's ExtendedModel).
    for kind in ('ekf', 'ukf'):
        assert isinstance(make_filter(load_preset('range-bearing'), kind).model, StepModel)
    assert not isinstance(object(), StepModel)


def test_predict_update_is_predict_then_update_to_the_bit():
    """Every model's one-call step gives the numbers of its two steps."""
    for preset, kind, fast, model in _every_estimator_model():
        if model.control_names:
            continue            # the estimator splits predictions at control stamps
        x = np.zeros(model.dim_x)
        x[0] = 3.0
        P = np.eye(model.dim_x)
        z = np.full(model.dim_z, 3.4)
        R = np.eye(model.dim_z) * 0.5
        one = model.predict_update(x, P, 0.1, z, R)
        two = model.update(*model.predict(x, P, 0.1), z, R)
        if kind in ('pf', 'bootstrap-pf'):
            # The particles behind x are drawn afresh from the seed at each call.
            two = model.update(*model.predict(x, P, 0.1), z, R)
            one = model.predict_update(x, P, 0.1, z, R)
        np.testing.assert_array_equal(one[0], two[0], err_msg=f'{preset} {kind} {fast}')
        np.testing.assert_array_equal(one[1], two[1], err_msg=f'{preset} {kind} {fast}')
        assert one[2].nis == two[2].nis


def test_which_step_runs_is_the_models_own_method():
    """The rail IMM has its own fused step; the others inherit predict-then-update."""
    rail = StreamEstimator(EstimatorSettings()).model
    assert type(rail).predict_update is IMMModel.predict_update
    train = StreamEstimator(EstimatorSettings(preset='train')).model
    assert type(train).predict_update is PredictThenUpdate.predict_update
    assert isinstance(train, PredictThenUpdate) and not isinstance(rail, PredictThenUpdate)


def _spy(model, calls):
    """Count the model's step calls by name in ``calls`` (instance attributes)."""
    for name in ('predict', 'update', 'predict_update'):
        method = getattr(model, name)

        def counted(*args, _method=method, _name=name, **kwargs):
            calls[_name] = calls.get(_name, 0) + 1
            return _method(*args, **kwargs)
        setattr(model, name, counted)


@pytest.mark.parametrize('preset', ['rail', 'train', 'cv-position'])
def test_fusion_fuses_an_in_order_measurement_with_one_predict_update(preset):
    """Without controls: one predict_update per in-order measurement, for every model."""
    estimator = StreamEstimator(EstimatorSettings(preset=preset, gate_probability=1.0))
    calls = {}
    _spy(estimator.model, calls)
    estimator.process(NS_PER_S, 1.0, 1.0)                       # initialises: no step
    assert 'predict_update' not in calls and 'update' not in calls
    for k in range(2, 6):
        estimator.process(k * NS_PER_S, float(k), 1.0)
    assert calls['predict_update'] == 4
    if preset == 'rail':
        # The rail IMM's is its own fused step: its predict and update are not called.
        assert 'predict' not in calls and 'update' not in calls
    else:
        # predict then update, inside the one call (the look-ahead may predict too).
        assert calls['update'] == 4 and calls['predict'] >= 4


def test_fusion_with_controls_predicts_at_the_control_stamps_then_updates():
    """A preset with a control input: predict (split at controls) then update."""
    estimator = StreamEstimator(EstimatorSettings(preset='car', gate_probability=1.0))
    calls = {}
    _spy(estimator.model, calls)
    estimator.add_control(NS_PER_S, [0.0])
    estimator.process(NS_PER_S, 0.0, 1.0)
    estimator.add_control(NS_PER_S + NS_PER_S // 2, [1.0])
    estimator.add_control(2 * NS_PER_S, [1.0])
    estimator.process(2 * NS_PER_S, 0.6, 1.0)
    assert 'predict_update' not in calls
    assert calls['update'] == 1 and calls['predict'] >= 2


def test_estimate_step_is_built_with_keywords_only():
    """Eleven positional fields are unreadable: EstimateStep refuses them."""
    fields = {'stamp_ns': 1, 'x': np.zeros(2), 'P': np.eye(2), 'update': None,
              'prediction_stamp_ns': 2, 'predicted_x': np.ones(2), 'predicted_P': np.eye(2)}
    step = EstimateStep(**fields)
    assert (step.measurement_stamp_ns, step.replayed, step.reset, step.control_stamp_ns) == (
        0, 0, None, 0)
    with pytest.raises(TypeError):
        EstimateStep(*fields.values())
    changed = step._replace(reset='stream_restart')
    assert type(changed) is EstimateStep and changed.reset == 'stream_restart'
    assert changed.predicted_x is step.predicted_x


def test_the_rail_model_overrides_no_private_part_of_the_imm():
    """The rail model specialises the IMM through its public hooks only."""
    private = [name for name in vars(IMM) if name.startswith('_') and not name.startswith('__')]
    assert private
    for name in private:
        assert getattr(RailModel, name) is getattr(IMM, name), name
    model = RailModel()
    assert model.mixing == model.mix_entering and model.stochastic
    assert model.matrices == model.matrices and model.transition == model.transition


def test_the_rail_entry_rule_gives_the_same_components_one_by_one_and_gathered():
    """One component's entry and the mixing's gather are the same table of the rule."""
    model = RailModel()
    rng = np.random.default_rng(3)
    means = rng.normal(size=(4, 6))
    covs = np.array([a @ a.T for a in rng.normal(size=(4, 6, 6))])
    xs, Ps = model._entry.components(means, covs)
    for j in range(4):
        for i in range(4):
            if i != j:
                x, P = model.entry(j, means[i], covs[i])
                np.testing.assert_array_equal(xs[j, i], x)
                np.testing.assert_array_equal(Ps[j, i].reshape(6, 6), P)


def test_one_formula_of_the_first_jump_for_floats_and_arrays():
    """first_jump_row of one row (floats) and of K rows (arrays), as RateTransition's."""
    rates = np.array([[0.0, 0.5, 0.1], [0.2, 0.0, 0.0], [0.0, 0.0, 0.0]])
    matrix = RateTransition(rates).matrix(0.25)
    for i in range(3):
        rows = first_jump_row(np.repeat(rates[i][None], 2, axis=0), i, 0.25)
        np.testing.assert_allclose(rows, np.repeat(matrix[i][None], 2, axis=0),
                                   rtol=1e-15, atol=0.0)
        assert first_jump_row(rates[i].tolist(), i, 0.25) == matrix[i].tolist()
    assert matrix[2].tolist() == [0.0, 0.0, 1.0]


def test_the_offline_series_runs_on_the_one_imm_running_state():
    """The offline series keeps its running state in an IMMFilter once started."""
    from kf_train.batch import RailSeriesFilter
    from kf_train.presets import load_rail_preset
    filt = RailSeriesFilter(load_rail_preset())
    assert filt._running is None and filt.update([5.0]) is None
    assert isinstance(filt._running, IMMFilter) and filt._running.imm is filt.imm
    filt.predict(0.1)
    snapshot = filt.snapshot()
    result = filt.update([5.2])
    copy = filt.copy()
    filt.restore(snapshot)
    assert filt.update([5.2]).nis == result.nis
    np.testing.assert_array_equal(filt.mean, copy.mean)
    assert copy._running is not filt._running


def test_one_stop_rule_for_the_node_and_the_tuner():
    """The stop rule of arrays (the tuner's settings) is the floats' element by element."""
    from kf_train.filters import stop_probability
    v = np.array([0.05, 15.0, 0.3, 0.2, -1.0])
    std = np.array([0.1, 0.2, 0.0, 0.0, 1e-3])
    many = stop_probability(v, std, 0.3)
    one_by_one = [stop_probability(a, b, 0.3) for a, b in zip(v.tolist(), std.tolist())]
    assert many.tolist() == one_by_one
    assert many[1] == 0.0 and many[2] == 1.0 and many[4] == 1.0
    assert many[0] == pytest.approx(0.9938, abs=1e-4)                  # Φ(2.5)


@pytest.mark.parametrize('preset', ['rail', 'train', 'cv-position-velocity'])
def test_r_keeps_one_shape_from_the_parameter_to_the_update(preset):
    """The override becomes the (m, m) R the model's update gets, unchanged on the way."""
    settings = EstimatorSettings(preset=preset, gate_probability=1.0, measurement_variance=2.0,
                                 measurement_velocity_variance=3.0)
    estimator = StreamEstimator(settings)
    seen = []
    step = estimator.model.predict_update

    def spied(x, P, dt_s, z, R=None):
        seen.append(R)
        return step(x, P, dt_s, z, R)
    estimator.model.predict_update = spied
    velocity = {'velocity_mps': 1.0, 'velocity_variance_m2s2': 0.5} if \
        estimator.model.dim_z == 2 else {}
    estimator.process(NS_PER_S, 1.0, 0.5, **velocity)
    estimator.process(2 * NS_PER_S, 2.0, 0.5, **velocity)
    (R,) = seen
    expected = estimator.measurement_noise(0.5, 0.5 if velocity else None)
    assert type(R) is np.ndarray and R.shape == (estimator.model.dim_z,) * 2
    assert R.tolist() == expected.tolist() and R[0, 0] == 2.0
