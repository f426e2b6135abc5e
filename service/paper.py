"""The paper's reported results (shared/docs/reference-problem.md, "Results to reproduce")."""

TABLE10_OFFSET = 2.77e4
"""Table 10 reports GoF and ln evidence minus this offset."""

TABLE10 = {
    "M1": {"goodness_of_fit": 37.81, "information_gain": 19.51, "log_evidence": 18.29, "probability": 0.0,
           "kept": ["a3", "a4"], "pruned": ["a5", "a6"]},
    "M2": {"goodness_of_fit": 135.55, "information_gain": 22.85, "log_evidence": 112.70, "probability": 1.0,
           "kept": ["a3", "a4"], "pruned": ["a5", "a6"]},
    "M3": {"goodness_of_fit": 129.42, "information_gain": 48.17, "log_evidence": 81.25, "probability": 0.0,
           "kept": ["a3", "a4"], "pruned": ["a5", "a6"]},
}

FIG15_M2OPT_BOUNDS = {
    "B": (0.186, 0.254), "a1": (-1.35, -1.13), "a2": (-1.15, -0.505), "a3": (83.1, 111.0),
    "a4": (-558.0, -449.0), "sigma": (1.79e-3, 3.64e-3),
}
"""99 % posterior bounds of M2opt reported in the paper's Fig. 15."""
