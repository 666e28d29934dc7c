"""
The update engine ``DSSLAC`` delegates its gradient steps to: one update as tensor ops (``gradient_step``), bursts of
them, eager or compiled (``bursts``), the allocator setting, and an op counter for measuring them. Imports
``sb3_dsslac.common`` and ``sb3_dsslac.nn``, never the algorithm above it.
"""
