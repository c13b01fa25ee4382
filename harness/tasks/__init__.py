"""The jobs ``python -m harness task=...`` runs, one module per ``conf/task/`` config."""
