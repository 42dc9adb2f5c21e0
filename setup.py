"""Packaging for the kf_train ament_python package."""

from glob import glob
import os

from setuptools import find_packages
from setuptools import setup

package_name = 'kf_train'


def _files(pattern):
    """Return the regular files matching ``pattern``, sorted."""
    return sorted(f for f in glob(pattern) if os.path.isfile(f))


data_files = [
    ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
    ('share/' + package_name, ['package.xml']),
]
_config = _files('config/*')
if _config:
    data_files.append(('share/' + package_name + '/config', _config))
_launch = _files('launch/*.launch.py')
if _launch:
    data_files.append(('share/' + package_name + '/launch', _launch))
_presets = _files('config/presets/*.yaml')
if _presets:
    data_files.append(('share/' + package_name + '/config/presets', _presets))

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={package_name: ['presets/*.yaml']},
    data_files=data_files,
    # What the installed package imports at run time, and nothing more. The ROS 2
    # wheels (rclpy, the message packages) are declared in package.xml and installed
    # from requirements-ros.txt: a ROS machine has them from its distribution.
    install_requires=['numpy', 'PyYAML'],
    extras_require={
        # kf-train plot and the demo's figures
        'plot': ['matplotlib'],
        # rosbag2 (MCAP, sqlite3) in and out: kf_train.io.bagio
        'bag': ['rosbags'],
        # kf-train replay's columnar path: CSV several times faster, Parquet in and out
        'fast': ['polars'],
        # kf-train replay --engine dask: fleets on a Dask cluster (pyarrow, pandas with it)
        'dask': ['dask[dataframe]', 'distributed', 'polars'],
        # kf-train tune's optimiser (kf_train.tune.noise_fit); never the nodes'
        'tune': ['scipy'],
        # a progress bar for long offline replays on a terminal: kf_train.replay.progress
        'progress': ['tqdm'],
        # NavSatFix on a track: kf_train.io.track_geometry's local transverse Mercator
        # (PROJ, the reference for map projections; wheels for every supported Python)
        'track': ['pyproj'],
        # the rail IMM compiled (kf_train.filters.rail_fast, opt-in: KF_TRAIN_JIT=1): the
        # default model's live step ~5x, bag replays ~2.3x faster; numpy's reference without
        'jit': ['numba'],
    },
    zip_safe=True,
    maintainer='kf_train maintainers',
    maintainer_email='maintainers@kf-train.example.org',
    description=(
        'Kalman filter estimation and prediction of a moving train: '
        'pure-Python core, simulator and estimator nodes'
    ),
    license='Apache-2.0',
    python_requires='>=3.10',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'simulator = kf_train.ros.simulator_node:main',
            'estimator = kf_train.ros.estimator_node:main',
            'kf-train = kf_train.cli:main',
        ],
    },
)
