"""Koopman vehicle harness: a MuJoCo sedan plant, learners, controllers and the Hydra app."""
