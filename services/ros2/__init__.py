"""The bridge to ROS 2 robots on rmw_zenoh, a service of its own (``aesop serve ros2``)."""
