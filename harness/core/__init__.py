"""The harness's core: what every layer shares and nothing else owns.

Owns the contracts (plant, lifted and linearisable models, controller: ``contracts``), the data
types (``Episode``, the min-max normalizer: ``episode``), the actuator limits (``limits``), the
reference path's geometry (``reference_path``), atomic files and run-directory locks
(``files``), the shared value checks (``checks``), the memory budget (``budget``) and the
repository's locations (``paths``).

Imports nothing else of the project (NumPy only): ``learners`` and ``controllers`` build on it
without loading the simulator or the recorder (``tests/test_imports.py``).
"""
