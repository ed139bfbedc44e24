"""The transferable push manipulation model (paper, §TPMM): one module per model of the paper.

``frames`` (contact and position frames, the shared currency), ``contact`` (manipulator and environment
contact models), ``position`` (the object position model), ``query`` (query densities on a new cloud),
``motion`` (motion models and their product of experts), ``bandwidth`` (bandwidths chosen by held-out
likelihood), ``library`` (a trained model, its file format, and a library of models chosen by H_r).
"""
