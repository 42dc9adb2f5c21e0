"""``kf-train simulate`` and the simulator's live parameters (max_samples, publish_clock, ...)."""

from pathlib import Path

from kf_train.io.bagio_types import TYPESTORE
import pytest
from test_simulate import read_bag, read_csv, simulate

NS = 1_000_000_000
CLOCK = 'rosgraph_msgs/msg/Clock'


def stamp_ns(time_msg):
    """Return a builtin_interfaces/Time as integer nanoseconds."""
    return time_msg.sec * NS + time_msg.nanosec


@pytest.mark.parametrize('name', ['run.mcap', 'run.csv'])
def test_max_samples_caps_the_duration(tmp_path, name):
    """-p max_samples:=N stops after N samples, as the node does; same first samples."""
    capped, full = tmp_path / ('capped-' + name), tmp_path / ('full-' + name)
    assert simulate('--duration', 10, '-p', 'max_samples:=7', '--output', capped) == 0
    assert simulate('--duration', 0.7, '--output', full) == 0
    if name.endswith('.csv'):
        assert read_csv(capped) == read_csv(full) and len(read_csv(capped)) == 7
    else:
        a, b = read_bag(capped), read_bag(full)
        assert len(a['/measurement'][1]) == 7
        for topic in ('/measurement', '/ground_truth'):
            assert [(t, TYPESTORE.serialize_cdr(m, a[topic][0]).tobytes())
                    for t, m in a[topic][1]] == [
                (t, TYPESTORE.serialize_cdr(m, b[topic][0]).tobytes()) for t, m in b[topic][1]]


def test_max_samples_alone_ends_the_run_and_something_must(tmp_path, capsys):
    """max_samples without --duration is a run of that many; neither is one line."""
    assert simulate('-p', 'max_samples:=4', '--output', tmp_path / 'run.csv') == 0
    assert len(read_csv(tmp_path / 'run.csv')) == 4
    capsys.readouterr()
    assert simulate('--output', tmp_path / 'none.csv') == 1
    err = capsys.readouterr().err.strip()
    assert '\n' not in err and '--duration' in err and 'max_samples' in err
    assert not (tmp_path / 'none.csv').exists()


def test_publish_clock_writes_the_jumped_stamps_first(tmp_path):
    """/clock holds every sample's stamp (clock jumps included), recorded before the rest."""
    out = tmp_path / 'run.mcap'
    assert simulate('--scenario', 'car', '--duration', 2, '-p', 'publish_clock:=true',
                    '-p', 'clock_jump_at_s:=1.0', '-p', 'clock_jump_s:=-0.5',
                    '--output', out) == 0
    topics = read_bag(out)
    kind, clocks = topics['/clock']
    assert kind == CLOCK and len(clocks) == 20
    truth = topics['/ground_truth'][1]
    assert [stamp_ns(m.clock) for _, m in clocks] == [stamp_ns(m.header.stamp)
                                                      for _, m in truth]
    assert [t for t, _ in clocks] == [t for t, _ in truth]
    assert stamp_ns(clocks[9][1].clock) == NS // 2  # sample 10 at 1.0 s, jumped back 0.5 s
    from rosbags.rosbag2 import Reader
    with Reader(out) as reader:
        order = [c.topic for c, _, _ in reader.messages()]
    assert order[:4] == ['/clock', '/control', '/measurement', '/ground_truth']


def test_publish_clock_with_a_csv_is_refused(tmp_path, capsys):
    """A CSV has no topic for /clock: one line, exit 1, no output."""
    assert simulate('--duration', 1, '-p', 'publish_clock:=true',
                    '--output', tmp_path / 'run.csv') == 1
    err = capsys.readouterr().err.strip()
    assert '\n' not in err and 'publish_clock' in err
    assert list(Path(tmp_path).iterdir()) == []


def test_min_subscribers_changes_nothing_offline(tmp_path):
    """min_subscribers only delays the live node's first sample: the same run."""
    assert simulate('--duration', 1, '-p', 'min_subscribers:=3',
                    '--output', tmp_path / 'a.csv') == 0
    assert simulate('--duration', 1, '--output', tmp_path / 'b.csv') == 0
    assert read_csv(tmp_path / 'a.csv') == read_csv(tmp_path / 'b.csv')
