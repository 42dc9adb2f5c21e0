"""
Floor 4, the ROS adapters: the only place that imports rclpy or message packages.

``messages`` converts between ROS messages and the core's numbers, ``parameters``
declares node parameters with descriptors, ``runner`` spins a node until SIGINT or
SIGTERM and exits cleanly, ``simulator_node`` and ``estimator_node`` are the nodes
(console scripts ``simulator`` and ``estimator``), ``demo_nodes`` the probe and the
parameter client of ``kf-train demo``. The modules are imported when used, not here:
``python -m kf_train.ros.estimator_node`` must find its module not yet imported.
"""

__all__ = ['demo_nodes', 'estimator_node', 'messages', 'parameters', 'runner',
           'simulator_node']
