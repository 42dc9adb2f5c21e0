"""
``kf-train tune BAG``: a rosbag2 bag (or Parquet) as input, the same as the equivalent CSV.

The bags are written without DDS: by ``kf-train simulate --output run.mcap`` (whose
``--output run.csv`` writes the same run as the replay CSV) and, for a q > 0, by the
simulator's bag writer fed a random-force train. Equality is exact: the bag reader
makes the same rows (t = stamp / 1e9, as the CSV's t; the same doubles), so the same
optimiser on the same likelihood returns the same numbers to the digit.
"""

import math

from kf_train.cli import main as kf_train_main
from kf_train.cli.tune import main as tune_main
from kf_train.io.bagio_output import odometry_message
from kf_train.io.bagio_simulation import SimulationBag
from kf_train.io.bagio_types import ODOMETRY, TYPESTORE
from kf_train.replay.bag import load_config
from kf_train.ros import estimator_params, param_spec
from kf_train.sim import cv_position_velocity_scenario, white_noise_acceleration_scenario
import numpy as np
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
import yaml

NS = 1_000_000_000


def simulate(*args):
    """Run ``kf-train simulate ARGS``; return the exit code."""
    return kf_train_main(['simulate'] + [str(a) for a in args])


def tune(capsys, *args):
    """Run ``kf-train tune ARGS``; return (exit code, stdout, stderr)."""
    argv = [str(a) for a in args]
    if '--preset' not in argv and '--config' not in argv:
        argv = ['--preset', 'train'] + argv        # the default is rail (test_tune_rail.py)
    code = tune_main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def estimates(text):
    """Return {parameter: (estimate, low, high)} from tune's report."""
    found = {}
    for line in text.splitlines():
        for name in ('process_noise_density', 'measurement_variance'):
            if f' {name} [' in line:
                value = line.split(']', 1)[1].split()[0]
                interval = line.split('[')[2].split(']')[0].split(', ')
                found[name] = (float(value), *map(float, interval))
    return found


def params(path):
    """Return the estimator's parameters in a params file."""
    return yaml.safe_load(open(path))['estimator']['ros__parameters']


def same_report(bag_text, csv_text):
    """Assert the two reports agree on every figure (not on the input lines)."""
    def figures(text):
        return [line for line in text.splitlines()
                if not line.startswith(('input:', 'maximum likelihood:', 'wrote '))]
    assert figures(bag_text) == figures(csv_text)


@pytest.mark.parametrize('scenario, preset', [('train', 'train'), ('car', 'car')])
def test_a_simulated_bag_tunes_as_its_csv(tmp_path, capsys, scenario, preset):
    """kf-train simulate's bag and CSV of one run: the same estimates, R as carried."""
    bag, table = tmp_path / 'run.mcap', tmp_path / 'run.csv'
    for output in (bag, table):
        assert simulate('--scenario', scenario, '--duration', 30, '--seed', 5,
                        '--output', output) == 0
    # R estimated on both
    code, bag_text, err = tune(capsys, bag, '--preset', preset, '--estimate-r',
                               '-o', tmp_path / 'bag.yaml')
    assert code == 0, err
    code, csv_text, err = tune(capsys, table, '--preset', preset, '-o', tmp_path / 'csv.yaml')
    assert code == 0, err
    same_report(bag_text, csv_text)
    assert params(tmp_path / 'bag.yaml') == params(tmp_path / 'csv.yaml')
    assert 'measurement_variance' in estimates(bag_text)
    assert '/measurement' in bag_text and 'truth from the bag' in bag_text
    assert '2-s prediction RMSE (279 rows with truth)' in bag_text
    if scenario == 'car':
        assert '/control' in bag_text
    # R as the messages carry it (1 m²), q alone estimated: as the CSV with --fix-r 1
    code, bag_text, err = tune(capsys, bag, '--preset', preset, '-o', tmp_path / 'bag.yaml')
    assert code == 0, err
    code, csv_text, err = tune(capsys, table, '--preset', preset, '--fix-r', 1.0,
                               '-o', tmp_path / 'csv.yaml')
    same_report(bag_text, csv_text)
    assert 'R = 1, as the messages carry it' in bag_text
    assert set(estimates(bag_text)) == {'process_noise_density'}
    # the node takes R from the messages: the bag's params file does not override it
    assert 'measurement_variance' not in params(tmp_path / 'bag.yaml')
    assert params(tmp_path / 'csv.yaml')['measurement_variance'] == 1.0


def _random_force_bag(path, q, rows, seed, reorder=()):
    """Write a random-force train (q) to a bag as the simulator would; return the scenario."""
    scenario = white_noise_acceleration_scenario(q, 1.0, rows, seed=seed)
    stamps = [round(t * NS) for t in scenario.t_s.tolist()]
    order = list(range(rows))
    for k in reorder:                          # published after the next one
        order[k], order[k + 1] = order[k + 1], order[k]
    with SimulationBag(path, None) as bag:
        for slot, k in enumerate(order):
            record_ns = stamps[slot]
            bag.write_measurement(record_ns, stamps[k], 'odom', float(scenario.z[k, 0]), 1.0)
            bag.write_truth(stamps[k], stamps[k], 'odom', 'base_link',
                            *map(float, scenario.truth[k]))
    return scenario


def _csv(path, scenario):
    """Write the scenario's replay CSV with truth."""
    path.write_text('t,z_position,true_position,true_velocity\n' + ''.join(
        f'{t!r},{z!r},{p!r},{v!r}\n' for t, z, (p, v) in zip(
            scenario.t_s.tolist(), scenario.z[:, 0].tolist(), scenario.truth.tolist())))


def test_q_from_a_bag_with_late_messages_and_the_params_file_replays(tmp_path, capsys):
    """A q > 0, messages out of order: the CSV's estimates; replay BAG and the node take them."""
    bag, table = tmp_path / 'run.mcap', tmp_path / 'run.csv'
    scenario = _random_force_bag(bag, 0.5, 300, seed=7, reorder=(10, 50, 200))
    _csv(table, scenario)
    code, bag_text, err = tune(capsys, bag, '--estimate-r', '-o', tmp_path / 'bag.yaml')
    assert code == 0, err
    code, csv_text, err = tune(capsys, table, '-o', tmp_path / 'csv.yaml')
    assert code == 0, err
    same_report(bag_text, csv_text)
    q, low, high = estimates(bag_text)['process_noise_density']
    assert 0.0 < low <= 0.5 <= high and q > 0.0
    tuned = params(tmp_path / 'bag.yaml')
    assert tuned == params(tmp_path / 'csv.yaml')
    # The node's parameter loader takes the file as it is ...
    config = estimator_params.load_estimator_config(
        [param_spec.read_params_file(str(tmp_path / 'bag.yaml'))])
    assert config.settings.process_noise_density == tuned['process_noise_density']
    assert config.settings.measurement_variance == tuned['measurement_variance']
    assert load_config([str(tmp_path / 'bag.yaml')], []) == config
    # ... and so does kf-train replay BAG, whose innovations are then consistent
    out = tmp_path / 'replayed.csv'
    assert kf_train_main(['replay', str(bag), '--params-file', str(tmp_path / 'bag.yaml'),
                          '--output', str(out)]) == 0
    nis = np.genfromtxt(out, delimiter=',', names=True)['nis']
    nis = nis[np.isfinite(nis)]
    # 99 % bounds of the mean of ~299 χ²(1) values: 1 ± 2.58·sqrt(2/299) = [0.79, 1.21]
    assert 0.79 < nis.mean() < 1.21


def test_a_backward_clock_jump_splits_the_bag_and_truth_can_be_missing(tmp_path, capsys):
    """Stamps jumping back start a new segment (the node resets); no truth topic: no RMSE."""
    bag = tmp_path / 'jump.mcap'
    assert simulate('--duration', 20, '--seed', 2, '-p', 'clock_jump_at_s:=10.05',
                    '-p', 'clock_jump_s:=-100.0', '--output', bag) == 0
    code, text, err = tune(capsys, bag, '--truth-topic', 'ground_truth',
                           '-o', tmp_path / 'p.yaml')
    assert code == 0, err
    assert '200 rows (2 objects), 198 innovations' in text
    assert '2 segments (stamps jumped back)' in text
    code, text, err = tune(capsys, bag, '--truth-topic', 'measurement',
                           '-o', tmp_path / 'p.yaml')
    assert code == 1 and 'truth topic /measurement has type' in err


@pytest.mark.parametrize('make, args, message', [
    (lambda path: None, [], 'no such file or directory'),
    (lambda path: path.write_bytes(b'\x89MCAP0\r\n'), [], 'not a readable bag'),
    ('train', ['--topic', 'odometry'], "measurement topic 'odometry' is not in the bag"),
    ('train', ['--preset', 'car'], 'no control topic'),
    ('train', ['--preset', 'cv-position-velocity'],
     'measurement topic /measurement has type geometry_msgs/msg/PoseWithCovarianceStamped'),
    ('train', ['--truth-topic', 'truth'], "truth topic 'truth' is not in the bag"),
])
def test_bad_bags_are_one_line(tmp_path, capsys, make, args, message):
    """Bad bags and topics: exit 1, kf-train replay's one-line message, no params file."""
    bag = tmp_path / 'run.mcap'
    if make == 'train':
        assert simulate('--duration', 1, '--output', bag) == 0
        capsys.readouterr()
    else:
        make(bag)
    code, out, err = tune(capsys, bag, '-o', tmp_path / 'p.yaml', *args)
    assert code == 1
    assert err.startswith('kf-train tune: error: ') and len(err.strip().splitlines()) == 1
    assert message in err and 'Traceback' not in err, err
    assert not (tmp_path / 'p.yaml').exists()


def test_parquet_tunes_as_the_csv(tmp_path, capsys):
    """A Parquet file with the CSV's columns gives the CSV's estimates; errors name the row."""
    polars = pytest.importorskip('polars')
    scenario = white_noise_acceleration_scenario(0.5, 1.0, 200, seed=3)
    _csv(tmp_path / 'in.csv', scenario)
    polars.read_csv(tmp_path / 'in.csv').write_parquet(tmp_path / 'in.parquet')
    code, parquet_text, err = tune(capsys, tmp_path / 'in.parquet', '-o', tmp_path / 'a.yaml')
    assert code == 0, err
    code, csv_text, err = tune(capsys, tmp_path / 'in.csv', '-o', tmp_path / 'b.yaml')
    same_report(parquet_text, csv_text)
    assert params(tmp_path / 'a.yaml') == params(tmp_path / 'b.yaml')
    frame = polars.read_csv(tmp_path / 'in.csv')
    frame = frame.with_columns(polars.when(polars.int_range(polars.len()) == 4)
                               .then(math.nan).otherwise(polars.col('z_position'))
                               .alias('z_position'))
    frame.write_parquet(tmp_path / 'bad.parquet')
    code, out, err = tune(capsys, tmp_path / 'bad.parquet', '-o', tmp_path / 'c.yaml')
    assert code == 1 and "bad.parquet row 5, column 'z_position'" in err, err


def test_a_sqlite3_bag_directory_tunes_as_the_mcap(tmp_path, capsys):
    """The same messages in a sqlite3 rosbag2 directory: the same estimates."""
    mcap, sqlite = tmp_path / 'run.mcap', tmp_path / 'run_db3'
    assert simulate('--duration', 20, '--seed', 4, '--output', mcap) == 0
    with Reader(mcap) as reader, Writer(sqlite, version=9,
                                        storage_plugin=StoragePlugin.SQLITE3) as writer:
        connections = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=TYPESTORE)
                       for c in reader.connections}
        for connection, record_ns, raw in reader.messages():
            writer.write(connections[connection.id], record_ns, raw)
    assert list(sqlite.glob('*.db3'))
    code, sqlite_text, err = tune(capsys, sqlite, '-o', tmp_path / 'a.yaml')
    assert code == 0, err
    code, mcap_text, err = tune(capsys, mcap, '-o', tmp_path / 'b.yaml')
    same_report(sqlite_text, mcap_text)
    assert 'bag run_db3: 200 measurements on /measurement' in sqlite_text


def test_odometry_measurements_give_both_variances(tmp_path, capsys):
    """cv-position-velocity reads Odometry: position and velocity, both variances carried."""
    scenario = cv_position_velocity_scenario(seed=2, n_samples=150)
    bag, table = tmp_path / 'odom.mcap', tmp_path / 'odom.csv'
    with Writer(bag.with_suffix(''), version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/measurement', ODOMETRY, typestore=TYPESTORE)
        for t, (p, v) in zip(scenario.t_s.tolist(), scenario.z.tolist()):
            stamp = round(t * NS)
            message = odometry_message(stamp, 'odom', 'base_link', [p, v],
                                       [[100.0, 0.0], [0.0, 100.0]])
            writer.write(connection, stamp, TYPESTORE.serialize_cdr(message, ODOMETRY))
    rows = zip(scenario.t_s.tolist(), scenario.z.tolist())
    table.write_text('t,z_position,z_velocity\n'
                     + ''.join(f'{t!r},{p!r},{v!r}\n' for t, (p, v) in rows))
    directory = bag.with_suffix('')
    code, bag_text, err = tune(capsys, directory, '--preset', 'cv-position-velocity',
                               '-o', tmp_path / 'a.yaml')
    assert code == 0, err
    assert 'R = 100, 100, as the messages carry it' in bag_text
    code, csv_text, err = tune(capsys, table, '--preset', 'cv-position-velocity',
                               '--fix-r', 100, 100, '-o', tmp_path / 'b.yaml')
    same_report(bag_text, csv_text)


def test_topic_options_apply_to_bags_only(tmp_path, capsys):
    """--topic with a CSV is a usage error (exit 2), as in kf-train replay."""
    _csv(tmp_path / 'in.csv', white_noise_acceleration_scenario(0.5, 1.0, 20, seed=1))
    with pytest.raises(SystemExit) as exit_info:
        tune_main(['--preset', 'train', str(tmp_path / 'in.csv'), '-o', str(tmp_path / 'p.yaml'),
                   '--topic', 'x'])
    assert exit_info.value.code == 2
    assert '--topic applies to a bag input only' in capsys.readouterr().err


def test_dropped_samples_tune_alike_in_the_csv_and_the_bag(tmp_path, capsys):
    """Dropout: the CSV's empty cells are left out, as the bag simply lacks them."""
    bag, table = tmp_path / 'drop.mcap', tmp_path / 'drop.csv'
    for output in (bag, table):
        assert simulate('--duration', 20, '--seed', 6, '-p', 'dropout_probability:=0.2',
                        '--output', output) == 0
    code, csv_text, err = tune(capsys, table, '--fix-r', 1.0, '-o', tmp_path / 'a.yaml')
    assert code == 0, err
    gaps = int(csv_text.split('input: ')[1].split(' rows without')[0])
    assert gaps > 10
    code, bag_text, err = tune(capsys, bag, '-o', tmp_path / 'b.yaml')
    assert code == 0, err
    assert f'preset train, {200 - gaps} rows' in bag_text
    same_report(bag_text, csv_text)
