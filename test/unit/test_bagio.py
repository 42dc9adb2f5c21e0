"""Rosbag2 in and out (kf_train.io.bagio, bagio_output, bagio_layout), without ROS."""

import math
import os
from pathlib import Path
import shutil
import subprocess
import sys

from kf_train.io import bagio
from kf_train.io.bagio_layout import FieldReader, PatchTemplate
from kf_train.io.bagio_output import ODOMETRY_FIELDS, odometry_message, OutputBag
from kf_train.io.bagio_types import (
    ACCEL, DIAGNOSTICS, ODOMETRY, POSE, TWIST, TWIST_COVARIANCE, TYPESTORE, VECTOR3)
from kf_train.sim.simulation import TrainSimulation
import numpy as np
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

T = TYPESTORE.types
NS = 1_000_000_000
PERIOD_NS = 100_000_000
LATENCY_NS = 1_234_567  # record time - stamp in the test bags
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'


# -- bags written with rosbags alone (independent of the module under test) ----------

def covariance_6x6(first_variance):
    """Return the nodes' 6x6 covariance: ``first_variance`` at [0], 1e9 on the diagonal."""
    covariance = [0.0] * 36
    for i in range(6):
        covariance[7 * i] = 1e9
    covariance[0] = first_variance
    return covariance


def header(stamp_ns, frame_id='odom'):
    """Return a rosbags std_msgs/Header."""
    sec, nanosec = divmod(stamp_ns, NS)
    return T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](
        sec=sec, nanosec=nanosec), frame_id=frame_id)


def vector3(x=0.0):
    """Return a rosbags Vector3 (x, 0, 0)."""
    return T['geometry_msgs/msg/Vector3'](x=x, y=0.0, z=0.0)


def pose_message(stamp_ns, position_m, variance_m2, frame_id='odom'):
    """Return a PoseWithCovarianceStamped as the simulator fills it."""
    covariance = np.array(covariance_6x6(variance_m2))
    pose = T['geometry_msgs/msg/Pose'](
        position=T['geometry_msgs/msg/Point'](x=position_m, y=0.0, z=0.0),
        orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0))
    return T[POSE](header=header(stamp_ns, frame_id), pose=T[
        'geometry_msgs/msg/PoseWithCovariance'](pose=pose, covariance=covariance))


def accel_message(stamp_ns, value):
    """Return an AccelStamped with accel.linear.x = value."""
    return T[ACCEL](header=header(stamp_ns, 'base_link'), accel=T['geometry_msgs/msg/Accel'](
        linear=vector3(value), angular=vector3()))


def twist_message(stamp_ns, value):
    """Return a TwistStamped with twist.linear.x = value."""
    return T[TWIST](header=header(stamp_ns, 'base_link'), twist=T['geometry_msgs/msg/Twist'](
        linear=vector3(value), angular=vector3()))


def write_bag(path, records, storage=StoragePlugin.MCAP):
    """Write ``records`` (topic, type, record_ns, message) into a rosbag2 directory."""
    connections = {}
    with Writer(path, version=9, storage_plugin=storage) as writer:
        for topic, kind, record_ns, message in records:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, kind, typestore=TYPESTORE)
            writer.write(connections[topic], record_ns, TYPESTORE.serialize_cdr(message, kind))
    return Path(path)


def seed_000():
    """Return seed 000's 100 measurements and their stamps [ns] (k · 0.1 s)."""
    positions = TrainSimulation(seed=0).generate(100).measured_position_m
    return positions, [k * PERIOD_NS for k in range(1, 101)]


def seed_records(topic='/measurement'):
    """Return seed 000 as bag records on ``topic``, recorded LATENCY_NS after the stamp."""
    positions, stamps = seed_000()
    return [(topic, POSE, stamp + LATENCY_NS, pose_message(stamp, float(z), 1.0))
            for z, stamp in zip(positions, stamps)]


def single_mcap(directory, target):
    """Move a one-file MCAP bag directory's file to ``target``; return it."""
    (source,) = Path(directory).glob('*.mcap')
    shutil.move(source, target)
    return Path(target)


def read_all(path, **kwargs):
    """Return every message BagInput yields for ``path``."""
    with bagio.BagInput(path, **kwargs) as bag:
        return list(bag.messages())


# -- reading ----------------------------------------------------------------------------

@pytest.mark.parametrize('form', ['mcap-directory', 'sqlite3-directory', 'mcap-file'])
def test_seed_000_round_trip_is_exact(tmp_path, form):
    """Seed 000's measurements come back bit for bit, in order, with both times."""
    storage = StoragePlugin.SQLITE3 if form.startswith('sqlite3') else StoragePlugin.MCAP
    path = write_bag(tmp_path / 'bag', seed_records(), storage)
    if form == 'mcap-file':
        path = single_mcap(path, tmp_path / 'seed000.mcap')
    positions, stamps = seed_000()
    with bagio.BagInput(path) as bag:
        assert (bag.measurement_topic, bag.control_topic) == ('/measurement', None)
        assert (bag.measurement_count, bag.control_count) == (100, 0)
        read = list(bag.messages())
    assert [m.stamp_ns for m in read] == stamps
    assert [m.record_ns for m in read] == [s + LATENCY_NS for s in stamps]
    assert np.array_equal([m.position_m for m in read], positions)  # exact, not close
    assert {(m.frame_id, m.variance_m2) for m in read} == {('odom', 1.0)}
    assert all(math.isnan(m.velocity_mps) and math.isnan(m.velocity_variance_m2s2)
               for m in read)


def test_odometry_measurements_and_controls_in_recorded_order(tmp_path):
    """Position-velocity measurements and controls interleave by record time."""
    records = []
    for k in range(1, 21):
        stamp = k * PERIOD_NS
        odometry = odometry_message(stamp, 'map', 'train', [k * 1.5, -2.0 - k],
                                    [[0.25 * k, 0.0], [0.0, 4.0]])
        records.append(('/train/odom', ODOMETRY, stamp + 10, odometry))
        records.append(('/control', ACCEL, stamp + 5, accel_message(stamp, 0.1 * k)))
    records.append(('/other', POSE, 7, pose_message(7, 1.0, 1.0)))  # ignored
    path = write_bag(tmp_path / 'bag', records)
    with bagio.BagInput(path, ODOMETRY, ACCEL, measurement_topic='/train/odom') as bag:
        assert (bag.measurement_count, bag.control_count) == (20, 20)
        read = list(bag.messages())
    assert [type(m) for m in read] == [bagio.Control, bagio.Measurement] * 20
    assert [m.record_ns for m in read] == sorted(m.record_ns for m in read)
    for k, (control, measurement) in enumerate(zip(read[::2], read[1::2]), start=1):
        assert control == bagio.Control(k * PERIOD_NS + 5, k * PERIOD_NS, 'base_link',
                                        0.1 * k)
        assert measurement == bagio.Measurement(k * PERIOD_NS + 10, k * PERIOD_NS, 'map',
                                                k * 1.5, 0.25 * k, -2.0 - k, 4.0)


@pytest.mark.parametrize('topics, expected', [
    (['/line1/measurement'], '/line1/measurement'),  # the one ending in /measurement
    (['/gnss/pose'], '/gnss/pose'),  # the only one of the type
    (['/measurement', '/gnss/pose'], '/measurement'),  # the name wins over the type
])
def test_default_topic_resolution(tmp_path, topics, expected):
    """Default 'measurement': /measurement, else */measurement, else the only typed one."""
    records = [(topic, POSE, 1 + i, pose_message(1, 2.0, 1.0)) for i, topic in enumerate(topics)]
    with bagio.BagInput(write_bag(tmp_path / 'bag', records)) as bag:
        assert bag.measurement_topic == expected


def test_robot_control_and_explicit_names(tmp_path):
    """A relative explicit name matches /name; TwistStamped controls for the robot."""
    records = [('/range', POSE, 2, pose_message(2, 0.5, 9e-4)),
               ('/speed', TWIST, 1, twist_message(2, 0.25))]
    read = read_all(write_bag(tmp_path / 'bag', records), control_type=TWIST,
                    measurement_topic='range', control_topic='/speed')
    assert read[0] == bagio.Control(1, 2, 'base_link', 0.25)
    assert read[1][:5] == (2, 2, 'odom', 0.5, 9e-4) and math.isnan(read[1].velocity_mps)
    assert len(read) == 2


def test_expected_types_follow_the_preset_names():
    """Position -> PoseWithCovarianceStamped, position+velocity -> Odometry; controls."""
    assert bagio.expected_types(('position',)) == (POSE, None)
    assert bagio.expected_types(('position', 'velocity')) == (ODOMETRY, None)
    assert bagio.expected_types(('position',), ('acceleration',)) == (POSE, ACCEL)
    assert bagio.expected_types(('position',), ('velocity',)) == (POSE, TWIST)
    with pytest.raises(ValueError, match='bearing'):
        bagio.expected_types(('bearing', 'range'))


# -- the learnt layouts equal rosbags ---------------------------------------------------

@pytest.mark.parametrize('little_endian', [True, False])
def test_field_reader_equals_rosbags_for_every_frame_length(little_endian):
    """Frames of 0..20 bytes (and non-ASCII), both byte orders: rosbags' values."""
    rng = np.random.default_rng(7)
    reader = FieldReader(POSE, bagio._FIELDS[POSE])
    frames = [''.join('abcdefghij'[i % 10] for i in range(n)) for n in range(21)]
    frames += ['gare_du_nord_é', 'ω']
    for repeat in range(3):
        for frame in frames:
            stamp = int(rng.integers(0, 2 ** 31 - 1)) * NS + int(rng.integers(0, NS))
            message = pose_message(stamp, float(rng.normal(0, 1e6)),
                                   float(rng.uniform(0, 10)), frame)
            raw = bytes(TYPESTORE.serialize_cdr(message, POSE, little_endian=little_endian))
            expected = TYPESTORE.deserialize_cdr(raw, POSE)
            frame_id, (sec, nanosec, position, variance) = reader.read(raw)
            assert frame_id == expected.header.frame_id == frame
            assert (sec, nanosec) == (expected.header.stamp.sec, expected.header.stamp.nanosec)
            assert (position, variance) == (expected.pose.pose.position.x,
                                            expected.pose.covariance[0])
    # Every key was learnt and is used (None would mean: rosbags for every message).
    assert reader._layouts and all(layout is not None for layout in reader._layouts.values())


def test_patch_templates_equal_rosbags():
    """Template bytes = rosbags' serialization of the whole message, byte for byte."""
    rng = np.random.default_rng(11)
    for frame_id, child in (('odom', 'base_link'), ('map', 'train_front')):
        template = PatchTemplate(odometry_message(0, frame_id, child, [0.0, 0.0],
                                                  [[0.0, 0.0], [0.0, 0.0]]), ODOMETRY,
                                 ODOMETRY_FIELDS)
        assert template.fast
        for _ in range(50):
            stamp = int(rng.integers(-2 ** 31, 2 ** 31)) * NS + int(rng.integers(0, NS))
            x = rng.normal(0, 1e4, 2)
            P = np.diag(rng.uniform(0, 100, 2))
            raw = bytes(template.fill(*divmod(stamp, NS), x[0], P[0, 0], x[1], P[1, 1]))
            full = odometry_message(stamp, frame_id, child, x, P)
            assert raw == bytes(TYPESTORE.serialize_cdr(full, ODOMETRY))


# -- writing ----------------------------------------------------------------------------

def test_output_bag_holds_the_standard_topics(tmp_path):
    """estimate/prediction/innovation//diagnostics, types, namespace, exact values."""
    path = tmp_path / 'out'
    x, P = np.array([12.5, 9.75]), np.array([[0.5, 0.1], [0.1, 0.25]])
    with OutputBag(path, namespace='/line1') as out:
        out.write_estimate(10, 3 * NS + 5, x, P)
        out.write_prediction(10, 5 * NS + 5, x + 1.0, P * 2.0)
        out.write_innovation(10, 3 * NS + 5, -0.5, 1.5, 0.25 / 1.5)
        out.write_diagnostics(11, 3 * NS, 'estimator: filter', 'kf_train', 'WARN', 'late',
                              [('received', '3'), ('fused', '2')])
        out.write_estimate(20, 4 * NS, [7.0], [[2.0]])  # a one-state estimate
        assert out.counts == {'estimate': 2, 'prediction': 1, 'innovation': 1,
                              'diagnostics': 1}
    with Reader(path) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {'/line1/estimate': ODOMETRY, '/line1/prediction': ODOMETRY,
                         '/line1/innovation': VECTOR3, '/diagnostics': DIAGNOSTICS}
        got = [(c.topic, t, TYPESTORE.deserialize_cdr(raw, c.msgtype))
               for c, t, raw in reader.messages()]
    assert [(topic, t) for topic, t, _ in got] == [
        ('/line1/estimate', 10), ('/line1/prediction', 10), ('/line1/innovation', 10),
        ('/diagnostics', 11), ('/line1/estimate', 20)]
    estimate, prediction, innovation, diagnostics, single = (m for _, _, m in got)
    assert (estimate.header.stamp.sec, estimate.header.stamp.nanosec) == (3, 5)
    assert (estimate.header.frame_id, estimate.child_frame_id) == ('odom', 'base_link')
    assert estimate.pose.pose.position.x == 12.5 and estimate.twist.twist.linear.x == 9.75
    assert list(estimate.pose.covariance) == covariance_6x6(0.5)
    assert list(estimate.twist.covariance) == covariance_6x6(0.25)
    assert estimate.pose.pose.orientation.w == 1.0
    assert prediction.pose.pose.position.x == 13.5 and prediction.pose.covariance[0] == 1.0
    assert (innovation.vector.x, innovation.vector.y, innovation.vector.z) == (
        -0.5, 1.5, 0.25 / 1.5)
    status = diagnostics.status[0]
    assert (status.level, status.name, status.message, status.hardware_id) == (
        1, 'estimator: filter', 'late', 'kf_train')
    assert [(v.key, v.value) for v in status.values] == [('received', '3'), ('fused', '2')]
    assert (single.twist.twist.linear.x, single.twist.covariance[0]) == (0.0, 1e9)


def test_a_stamp_beyond_a_ros_time_is_refused(tmp_path):
    """ROS Time has int32 seconds: a later stamp raises ValueError, no output."""
    with pytest.raises(ValueError, match='out of range of a ROS stamp'):
        with OutputBag(tmp_path / 'run.mcap') as out:
            out.write_prediction(1, 2 ** 31 * NS, [1.0, 2.0], [[1.0, 0.0], [0.0, 1.0]])
    with pytest.raises(ValueError, match='out of range of a ROS stamp'):
        with OutputBag(tmp_path / 'run.mcap') as out:
            out.write_innovation(1, -2 ** 31 * NS - 1, 0.0, 1.0, 0.0)
    assert os.listdir(tmp_path) == []


def test_single_mcap_output_replaces_a_file_and_leaves_nothing_else(tmp_path):
    """X.mcap: one readable MCAP file, an old one replaced, no temporary left."""
    target = tmp_path / 'run.mcap'
    target.write_text('old')
    with OutputBag(target) as out:
        out.write_estimate(1, 1, [1.0, 2.0], [[1.0, 0.0], [0.0, 1.0]])
    assert sorted(os.listdir(tmp_path)) == ['run.mcap']
    with Reader(target) as reader:
        assert reader.message_count == 1


def test_an_exception_leaves_no_output(tmp_path):
    """A failure inside the with block: no bag, no temporary directory."""
    with pytest.raises(RuntimeError):
        with OutputBag(tmp_path / 'run.mcap') as out:
            out.write_estimate(1, 1, [1.0, 2.0], [[1.0, 0.0], [0.0, 1.0]])
            raise RuntimeError('replay failed')
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize('case, words', [
    ('missing-directory', ['does not exist']),
    ('existing-bag-directory', ['exists']),
    ('unwritable-directory', ['not writable']),
])
def test_output_problems_are_one_line(tmp_path, case, words):
    """Where a bag cannot be written: a one-line ValueError naming the path."""
    target = tmp_path / 'out'
    if case == 'missing-directory':
        target = tmp_path / 'nowhere' / 'out.mcap'
    elif case == 'existing-bag-directory':
        target.mkdir()
    else:
        locked = tmp_path / 'locked'
        locked.mkdir()
        locked.chmod(0o500)
        target = locked / 'out.mcap'
        if os.access(locked, os.W_OK):  # root ignores permissions
            locked.chmod(0o700)
            pytest.skip('running as root: permissions are not enforced')
    with pytest.raises(ValueError) as error:
        OutputBag(target)
    assert str(target) in str(error.value) and '\n' not in str(error.value)
    for word in words:
        assert word in str(error.value)


# -- bad bags ---------------------------------------------------------------------------

def truncated(source, target, fraction):
    """Write the first ``fraction`` of ``source``'s bytes to ``target``."""
    data = Path(source).read_bytes()
    Path(target).write_bytes(data[:int(len(data) * fraction)])
    return Path(target)


def bad_bag(tmp_path, case):
    """Return (path, keyword arguments) of a bad bag of kind ``case``."""
    good = write_bag(tmp_path / 'good', seed_records())
    (good_mcap,) = good.glob('*.mcap')
    if case == 'missing-path':
        return tmp_path / 'nothing.mcap', {}
    if case == 'text-file-named-mcap':
        (tmp_path / 'notes.mcap').write_text('not a bag\n')
        return tmp_path / 'notes.mcap', {}
    if case == 'csv-file':
        (tmp_path / 'data.csv').write_text('t,z_position\n0.1,1.0\n')
        return tmp_path / 'data.csv', {}
    if case == 'directory-without-metadata':
        (tmp_path / 'empty').mkdir()
        return tmp_path / 'empty', {}
    if case == 'truncated-mcap-file':
        return truncated(good_mcap, tmp_path / 'cut.mcap', 0.6), {}
    if case == 'truncated-mcap-in-directory':
        truncated(good_mcap, good_mcap.with_suffix('.part'), 0.6)
        os.replace(good_mcap.with_suffix('.part'), good_mcap)
        return good, {}
    if case == 'truncated-sqlite3':
        bag = write_bag(tmp_path / 'sql', seed_records(), StoragePlugin.SQLITE3)
        (db3,) = bag.glob('*.db3')
        truncated(db3, db3, 0.5)
        return bag, {}
    if case == 'missing-topic':
        return write_bag(tmp_path / 'other', [('/gps', ACCEL, 1, accel_message(1, 0.0))]), {}
    if case == 'wrong-type':
        message = T[POSE_STAMPED](header=header(1), pose=pose_message(1, 0.0, 1.0).pose.pose)
        return write_bag(tmp_path / 'wrong', [('/measurement', POSE_STAMPED, 1, message)]), {}
    if case == 'two-candidates':
        return write_bag(tmp_path / 'two', [('/a', POSE, 1, pose_message(1, 0.0, 1.0)),
                                            ('/b', POSE, 2, pose_message(2, 0.0, 1.0))]), {}
    if case == 'missing-control':
        return good, {'control_type': ACCEL}
    if case == 'explicit-topic-missing':
        return good, {'measurement_topic': '/gnss'}
    raise AssertionError(case)


BAD_BAGS = {
    'missing-path': ['no such file'],
    'text-file-named-mcap': ['not a readable bag'],
    'csv-file': ['not a bag'],
    'directory-without-metadata': ['no metadata.yaml'],
    'truncated-mcap-file': ['truncated'],
    'truncated-mcap-in-directory': ['truncated'],
    'truncated-sqlite3': ['truncated'],
    'missing-topic': ['no measurement topic', POSE, '/gps'],
    'wrong-type': ['/measurement', POSE_STAMPED, 'expected ' + POSE],
    'two-candidates': ['/a', '/b', 'choose'],
    'missing-control': ['no control topic', ACCEL],
    'explicit-topic-missing': ["'/gnss'", 'not in the bag', '/measurement'],
}


@pytest.mark.parametrize('case', sorted(BAD_BAGS))
def test_bad_bags_raise_one_line_naming_the_problem(tmp_path, case):
    """Every bad bag: ValueError, one line, the bag's path and the problem in it."""
    path, kwargs = bad_bag(tmp_path, case)
    with pytest.raises(ValueError) as error:
        read_all(path, **kwargs)
    text = str(error.value)
    assert '\n' not in text and text.startswith(str(path)), text
    for word in BAD_BAGS[case]:
        assert word in text, (word, text)


def test_a_message_that_does_not_decode_names_it(tmp_path):
    """A cut message inside an intact bag: the error names its index and topic."""
    path = tmp_path / 'bag'
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection('/measurement', POSE, typestore=TYPESTORE)
        for k in range(1, 4):
            raw = bytes(TYPESTORE.serialize_cdr(pose_message(k, 1.0, 1.0), POSE))
            writer.write(connection, k, raw[:40] if k == 3 else raw)
    with bagio.BagInput(path) as bag:
        stream = bag.messages()
        assert [next(stream).stamp_ns, next(stream).stamp_ns] == [1, 2]
        with pytest.raises(ValueError, match=r'message 3 on /measurement does not decode'):
            next(stream)


def test_bad_arguments(tmp_path):
    """Unsupported types are refused before the bag is opened."""
    path = write_bag(tmp_path / 'bag', seed_records())
    with pytest.raises(ValueError, match='measurement_type'):
        bagio.BagInput(path, measurement_type=ACCEL)
    with pytest.raises(ValueError, match='control_type'):
        bagio.BagInput(path, control_type=POSE)


def test_bag_modules_import_no_ros():
    """kf_train.io.bagio* need rosbags only: no rclpy, no ROS message package."""
    code = ('import sys, kf_train.io.bagio, kf_train.io.bagio_output\n'
            'print(sorted({m.split(".")[0] for m in sys.modules} & {"rclpy", "scipy", '
            '"rcl_interfaces", "geometry_msgs", "nav_msgs", "diagnostic_msgs"}))')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=60, check=True)
    assert result.stdout.strip() == '[]'


def speed_message(stamp_ns, speed_mps, variance):
    """Return a TwistWithCovarianceStamped with a speed and its variance."""
    twist = T['geometry_msgs/msg/Twist'](linear=vector3(speed_mps), angular=vector3())
    return T[TWIST_COVARIANCE](
        header=header(stamp_ns, 'base_link'), twist=T['geometry_msgs/msg/TwistWithCovariance'](
            twist=twist, covariance=np.array(covariance_6x6(variance))))


def test_speeds_are_read_from_their_topic_and_left_out_unless_asked(tmp_path):
    """The velocity topic: its type read, by default the bag's /velocity if so typed."""
    records = [('/measurement', POSE, 2, pose_message(1, 3.0, 1.0)),
               ('/velocity', TWIST_COVARIANCE, 3, speed_message(1, 4.5, 0.04)),
               ('/odom/speed', TWIST, 4, twist_message(1, 4.0))]
    path = write_bag(tmp_path / 'bag', records)
    read = read_all(path, velocity_type=TWIST_COVARIANCE)
    assert read[1] == bagio.Velocity(3, 1, 'base_link', 4.5, 0.04) and len(read) == 2
    assert len(read_all(path)) == 1                            # no speeds asked for
    assert len(read_all(path, velocity_type=TWIST)) == 1       # /velocity has another type
    twist = read_all(path, velocity_type=TWIST, velocity_topic='odom/speed')[1]
    assert twist[:4] == (4, 1, 'base_link', 4.0) and math.isnan(twist.variance_m2s2)
    for kwargs, words in (({'velocity_type': TWIST_COVARIANCE, 'velocity_topic': 'none'},
                           'not in the bag'),
                          ({'velocity_type': TWIST_COVARIANCE, 'velocity_topic': 'odom/speed'},
                           'has type'),
                          ({'velocity_topic': 'velocity'}, 'fuses no speed')):
        with pytest.raises(ValueError, match=words):
            read_all(path, **kwargs)
