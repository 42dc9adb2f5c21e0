"""The standard message types kf_train's bags hold, and the rosbags typestore for them."""

from rosbags.typesys import get_typestore, Stores

POSE = 'geometry_msgs/msg/PoseWithCovarianceStamped'
ODOMETRY = 'nav_msgs/msg/Odometry'
ACCEL = 'geometry_msgs/msg/AccelStamped'
TWIST = 'geometry_msgs/msg/TwistStamped'
TWIST_COVARIANCE = 'geometry_msgs/msg/TwistWithCovarianceStamped'
VECTOR3 = 'geometry_msgs/msg/Vector3Stamped'
DIAGNOSTICS = 'diagnostic_msgs/msg/DiagnosticArray'
NAVSATFIX = 'sensor_msgs/msg/NavSatFix'
"""The measurement type of ``measurement_type`` navsatfix (kf_train.ros.track_input)."""

MEASUREMENT_TYPES = {('position',): POSE, ('position', 'velocity'): ODOMETRY}
"""A preset's measurement names -> the message type of its ``measurement`` topic."""
CONTROL_TYPES = {'acceleration': ACCEL, 'velocity': TWIST}
"""A preset's control name -> the message type of its ``control`` topic."""
VELOCITY_TYPES = {'twist_with_covariance': TWIST_COVARIANCE, 'twist': TWIST}
"""The estimator's ``velocity_type`` -> the message type of its ``velocity`` topic."""

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
"""rosbags' definitions of the ROS 2 Jazzy standard messages."""

UNESTIMATED_VARIANCE = 1e9
"""Variance of the dimensions the 1-D model does not estimate (as kf_train/messages.py)."""

DIAGNOSTIC_LEVELS = {'OK': 0, 'WARN': 1, 'ERROR': 2, 'STALE': 3}
"""diagnostic_msgs/DiagnosticStatus levels by name (as kf_train/messages.py)."""
