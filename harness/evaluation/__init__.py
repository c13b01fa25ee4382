"""How a fitted model is judged: open-loop prediction of the test drives (``prediction``), steps
of steering (``step_response``), the lifted operator's spectrum (``spectrum``), closed-loop
tracking (``tracking``) and the networks' training curves (``training_report``).

May import ``harness.core``, ``harness.plant`` (rollouts), ``harness.references``,
``harness.output``, ``harness.recorder`` and ``learners``; the tasks build on it.
"""
