"""The vehicle model files: ``mjcf/``, the MuJoCo models the plant loads (``harness/plant/``).

Data, not code: a package only so that an installed harness ships them beside ``conf/``.
"""
