"""Applications built on the kernel API and the control loop: the ``dyq`` command line and the demo."""
