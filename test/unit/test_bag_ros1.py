"""A ROS 1 .bag (written here by rosbags) replays as the same messages in a rosbag2 bag."""

from pathlib import Path

from kf_train.cli import main as kf_train_main
from kf_train.io import is_bag
from kf_train.io.bagio_types import POSE, TWIST_COVARIANCE
import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.typesys import get_typestore, Stores

NS = 1_000_000_000
PERIOD_NS = 200_000_000
LATENCY_NS = 3_000_000


def _messages(store, count=150, seed=3):
    """Return (topic, type, record_ns, message) of a train run: fixes and speeds."""
    types = store.types
    rng = np.random.default_rng(seed)
    speed = np.clip(np.cumsum(rng.normal(0.0, 0.3, count)) + 8.0, 0.0, None)
    position = np.cumsum(speed) * PERIOD_NS / NS
    has_seq = 'seq' in types['std_msgs/msg/Header'].__dataclass_fields__
    records = []
    for k in range(count):
        stamp = (k + 1) * PERIOD_NS
        sec, nanosec = divmod(stamp, NS)
        fields = {'seq': k} if has_seq else {}
        header = types['std_msgs/msg/Header'](
            stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec),
            frame_id='odom', **fields)
        covariance = np.zeros(36)
        covariance[0] = 4.0
        pose = types['geometry_msgs/msg/Pose'](
            position=types['geometry_msgs/msg/Point'](
                x=float(position[k] + rng.normal(0.0, 2.0)), y=0.0, z=0.0),
            orientation=types['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0))
        records.append(('/measurement', POSE, stamp + LATENCY_NS, types[POSE](
            header=header, pose=types['geometry_msgs/msg/PoseWithCovariance'](
                pose=pose, covariance=covariance))))
        twist_covariance = np.zeros(36)
        twist_covariance[0] = 0.04
        vector = types['geometry_msgs/msg/Vector3']
        twist = types['geometry_msgs/msg/Twist'](
            linear=vector(x=float(speed[k] + rng.normal(0.0, 0.2)), y=0.0, z=0.0),
            angular=vector(x=0.0, y=0.0, z=0.0))
        records.append(('/velocity', TWIST_COVARIANCE, stamp + 2 * LATENCY_NS,
                        types[TWIST_COVARIANCE](
                            header=header, twist=types['geometry_msgs/msg/TwistWithCovariance'](
                                twist=twist, covariance=twist_covariance))))
    return records


def _write_ros1(path: Path) -> Path:
    """Write the run as a ROS 1 bag, with Noetic's types (a Header with seq)."""
    store = get_typestore(Stores.ROS1_NOETIC)
    connections = {}
    with Ros1Writer(path) as writer:
        for topic, kind, record_ns, message in _messages(store):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, kind, typestore=store)
            writer.write(connections[topic], record_ns, store.serialize_ros1(message, kind))
    return path


def _write_ros2(path: Path) -> Path:
    """Write the same run as a rosbag2 (MCAP) bag, with Jazzy's types."""
    store = get_typestore(Stores.ROS2_JAZZY)
    connections = {}
    with Ros2Writer(path, version=9) as writer:
        for topic, kind, record_ns, message in _messages(store):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, kind, typestore=store)
            writer.write(connections[topic], record_ns, store.serialize_cdr(message, kind))
    return path


def test_a_ros1_bag_replays_as_its_rosbag2_twin(tmp_path, capsys):
    """The default (rail, speeds fused) over a ROS 1 bag: the rosbag2 replay's bytes."""
    ros1 = _write_ros1(tmp_path / 'run.bag')
    ros2 = _write_ros2(tmp_path / 'run2')
    assert is_bag(str(ros1))
    for name, bag in (('one', ros1), ('two', ros2)):
        assert kf_train_main(['replay', str(bag), '-o', str(tmp_path / f'{name}.csv')]) == 0
        assert kf_train_main(['replay', str(bag), '-o', str(tmp_path / f'{name}.mcap')]) == 0
    err = capsys.readouterr().err
    assert err.count('150 measurements on /measurement') == 4
    assert err.count('150 speeds on /velocity') == 4
    one, two = (tmp_path / 'one.csv').read_bytes(), (tmp_path / 'two.csv').read_bytes()
    assert one == two and one.count(b'\n') > 150   # estimates after fixes and speeds
    from rosbags.rosbag2 import Reader
    outputs = []
    for name in ('one', 'two'):
        with Reader(tmp_path / f'{name}.mcap') as reader:
            outputs.append([(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()])
    assert outputs[0] == outputs[1] and len(outputs[0]) > 600


def test_a_damaged_ros1_bag_is_one_line(tmp_path, capsys):
    """A .bag that is not one: exit 1, one line naming it, nothing written."""
    bad = tmp_path / 'bad.bag'
    bad.write_bytes(b'#ROSBAG V2.0\n' + b'\x00' * 40)
    assert kf_train_main(['replay', str(bad), '-o', str(tmp_path / 'o.csv')]) == 1
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'bad.bag' in err
    assert not (tmp_path / 'o.csv').exists()


def test_plot_a_bag_replay_with_the_bag_as_input(tmp_path, capsys):
    """kf-train plot --replay OUT.csv --input BAG: the fixes come from the replayed bag."""
    pytest.importorskip('matplotlib')
    from kf_train.plots.figures import _bag_fixes
    bag = _write_ros1(tmp_path / 'run.bag')
    assert kf_train_main(['replay', str(bag), '-o', str(tmp_path / 'out.csv')]) == 0
    times, positions = _bag_fixes(str(bag))
    assert times.shape == (150,) and times[0] == PERIOD_NS / NS     # the header stamps
    assert kf_train_main(['plot', '--replay', str(tmp_path / 'out.csv'), '--input', str(bag),
                          '-o', str(tmp_path)]) == 0
    (path,) = capsys.readouterr().out.split()
    assert path.endswith('out.png') and (tmp_path / 'out.png').stat().st_size > 10_000


def test_an_output_bag_reads_as_the_csv(tmp_path, capsys):
    """The output bag's columns (read for kf-train plot) are the CSV output's numbers."""
    pytest.importorskip('matplotlib')
    from kf_train.io.bagio_output import read_output_bag
    bag = _write_ros1(tmp_path / 'run.bag')
    assert kf_train_main(['replay', str(bag), '-o', str(tmp_path / 'out.csv')]) == 0
    assert kf_train_main(['replay', str(bag), '-o', str(tmp_path / 'out.mcap')]) == 0
    columns = read_output_bag(tmp_path / 'out.mcap')
    with open(tmp_path / 'out.csv') as stream:
        header = stream.readline().strip().split(',')
        rows = np.array([[float(c) if c else np.nan for c in line.strip().split(',')]
                         for line in stream])
    for name, values in columns.items():
        expected = rows[:, header.index(name)]
        if name == 't':     # stamps as sec + nanosec / 1e9 against ns / 1e9: to 1 ulp
            np.testing.assert_allclose(values, expected, rtol=1e-15, atol=0)
        else:
            np.testing.assert_array_equal(values, expected, err_msg=name)
    assert 'p_stand' in columns and 'nis' in columns
    assert kf_train_main(['plot', '--replay', str(tmp_path / 'out.mcap'), '--input', str(bag),
                          '-o', str(tmp_path)]) == 0
    assert capsys.readouterr().out.split()[-1].endswith('out.png')
