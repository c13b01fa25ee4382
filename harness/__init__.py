"""Koopman vehicle harness: a MuJoCo sedan plant, learners, controllers and the Hydra app.

The layers, bottom up (the allowed arrows are listed once, in ``tests/test_imports.py``):
``harness.core``; ``learners``, ``controllers``, ``harness.plant``, ``harness.output``,
``harness.recorder``; ``harness.references``, ``harness.data``, ``harness.evaluation``;
``harness.config``, ``harness.tasks``, ``harness.report``; ``harness.app``.
"""
