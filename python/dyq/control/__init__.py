"""The control loop: the kinematic dispatcher, the precision flag and the per-step runtime."""
