"""Learners of x_{k+1} = f(x_k, u_k): EDMD, ELM-EDMD, DNN and Deep EDMD (issue: the four learners).

Nothing lives here yet: the plant and the data come first.
"""
