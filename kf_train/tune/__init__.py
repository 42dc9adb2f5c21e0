"""
Floor 5, noise fitting: ``kf-train tune``'s work, by maximum likelihood of the innovations.

* :mod:`~kf_train.tune.noise_fit`: q and R of the linear presets (scipy's optimiser,
  imported when a fit runs: the extra of ``kf-train tune``);
* :mod:`~kf_train.tune.rail_fit`: the rail IMM's noises (scipy too);
* :mod:`~kf_train.tune.inputs`: the data, from a CSV, Parquet or a bag, as segments;
* :mod:`~kf_train.tune.linear` and :mod:`~kf_train.tune.rail`: the workflows (fit, check
  before and after, write the params file and the tuned preset);
* :mod:`~kf_train.tune.validation`: the rail preset's hold-out, the node's own
  estimator scoring a setting there, and the plain-words verdict on the innovations.
"""

from kf_train.tune.inputs import read_bag, reader_for, TopicOptions, TuneInput
from kf_train.tune.linear import (
    carried_variances, params_yaml, tune_linear, TuneOptions)
from kf_train.tune.noise_fit import estimate_noise, TuningResult
from kf_train.tune.rail import DEFAULT_NOISES, rail_preset_of, TUNABLE_NOISES, tune_rail
from kf_train.tune.rail_fit import fit_rail_noise, RailFit
from kf_train.tune.validation import (
    Comparison, DEFAULT_HOLDOUT, Holdout, MIN_SPLIT_S, model_verdict, score_setting,
    SettingScore, split_holdout)

__all__ = [
    'carried_variances', 'Comparison', 'DEFAULT_HOLDOUT', 'DEFAULT_NOISES', 'estimate_noise',
    'fit_rail_noise', 'Holdout', 'MIN_SPLIT_S', 'model_verdict', 'params_yaml', 'RailFit',
    'rail_preset_of', 'read_bag', 'reader_for', 'score_setting', 'SettingScore',
    'split_holdout', 'TopicOptions', 'tune_linear', 'tune_rail', 'TuneInput', 'TuneOptions',
    'TuningResult', 'TUNABLE_NOISES',
]
