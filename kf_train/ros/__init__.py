"""
Floor 4, the ROS adapters: the only place that imports rclpy or message packages.

``messages`` converts between ROS messages and the core's numbers; ``param_spec`` is
the pure parameter table (one ParamSpec per parameter: declaration, validation,
config yaml, docs/ros.md, ``ros2 param describe``), ``simulator_params`` and
``estimator_params`` the two nodes' tables, ``param_docs`` their text, ``parameters``
declares them on a node; ``diagnostics`` builds the estimator's status (pure);
``session`` is what the estimator node does with its input (pure, shared with the bag
replay);
``runner`` spins a node until SIGINT or SIGTERM and exits cleanly; ``simulator_node``
and ``estimator_node`` are the nodes (console scripts ``simulator`` and
``estimator``); ``demo_nodes`` the probe and the parameter client of ``kf-train demo``.
The modules are imported when used, not here: ``python -m kf_train.ros.estimator_node``
must find its module not yet imported, and the pure modules must import without rclpy.
"""

__all__ = ['demo_nodes', 'diagnostics', 'estimator_node', 'estimator_params', 'messages',
           'param_docs', 'param_spec', 'parameters', 'runner', 'session', 'simulator_node',
           'simulator_params']
