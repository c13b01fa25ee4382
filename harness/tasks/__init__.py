"""The jobs ``python -m harness task=...`` runs, one module per ``conf/task/`` config.

The top of the harness: may import ``learners``, ``controllers``, ``harness.core``,
``harness.config``, ``harness.plant``, ``harness.data``, ``harness.references``,
``harness.evaluation``, ``harness.output`` and ``harness.recorder``.
"""
