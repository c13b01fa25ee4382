"""Controllers that act on the plant: the Koopman MPC (DE-MPC) solved with PIQP (issue: DE-MPC).

Nothing lives here yet: it needs a learned lifted-linear model first.
"""
