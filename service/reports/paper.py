"""The paper's reported results (docs/worked-example.md, "What the paper reports")."""

from ardflow.ardcore.sampling.diagnostics import Quality

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


DOCUMENTED_DIFFERENCES = {
    ("M1", "a3"): "the paper keeps a3 in the quasi-steady M1; here the evidence prunes it on every seed tried "
                  "(a4 takes its role in a model without the aerodynamic lag), and an independent implementation "
                  "agrees: an accepted, documented difference (docs/select.md, 'Why M1 drops a3')",
}
"""(model, term) -> why this project's result differs from the paper's and is accepted."""


def check_label(c: dict) -> str:
    """PASS, FAIL or DOCUMENTED (a documented difference from the paper) for one check."""
    return "DOCUMENTED" if c.get("documented") else ("PASS" if c["passed"] else "FAIL")


def reference_checks(summary: dict, true_values: dict) -> list[dict]:
    """The checks of a Section 3.6 summary against the paper (docs/worked-example.md, "What the paper reports").

    Returns a list of ``{"check", "passed", "detail", "documented"}``: P(M2opt) >= 0.99; a5 and a6 pruned
    in every model; a3 and a4 kept in every model; every true parameter inside M2opt's 99 % bounds. A
    check that fails only by a difference listed in :data:`DOCUMENTED_DIFFERENCES` passes with
    ``documented`` set to its reason.
    """
    rows = {r["name"]: r for r in summary.get("models", [])}
    out = []
    m2 = rows.get("M2")
    if m2 is None:
        return [{"check": "M2 in the study", "passed": False, "detail": f"models: {sorted(rows)}"}]
    out.append({"check": "P(M2opt) >= 0.99", "passed": m2.get("probability", 0) >= 0.99,
                "detail": f"P = {m2.get('probability', 0):.4f}"})
    for name, r in rows.items():
        pruned, kept = set(r.get("pruned", [])), set(r.get("kept", []))
        out.append({"check": f"{name}: a5, a6 pruned", "passed": {"a5", "a6"} <= pruned,
                    "detail": f"pruned {sorted(pruned)}"})
        missing = {"a3", "a4"} - kept
        why = [DOCUMENTED_DIFFERENCES[(name, t)] for t in sorted(missing) if (name, t) in DOCUMENTED_DIFFERENCES]
        documented = "; ".join(why) if missing and len(why) == len(missing) else None
        out.append({"check": f"{name}: a3, a4 kept", "passed": not missing or documented is not None,
                    "detail": f"kept {sorted(kept)}", "documented": documented})
    for name, r in rows.items():
        # the intervals and the evidence rest on these draws: convergence by today's standard (ArviZ)
        diag = r.get("diagnostics") or {}
        if diag:
            worst_r, worst_e, _, _ = Quality().worst(diag)
            detail = f"max R-hat {worst_r:.3f}, min bulk/tail ESS {worst_e:.0f}"
        else:
            detail = "no diagnostics"
        out.append({"check": f"{name}: posterior converged (R-hat <= 1.01, ESS >= 400)",
                    "passed": bool(diag) and bool(r.get("converged", False)), "detail": detail})
    outside = []
    for p, v in true_values.items():
        if p in m2.get("q005", {}):
            lo, hi = m2["q005"][p], m2["q995"][p]
            if not lo <= v <= hi:
                outside.append(f"{p}={v:g} not in [{lo:.4g}, {hi:.4g}]")
    out.append({"check": "true values inside M2opt's 99 % bounds", "passed": not outside,
                "detail": "; ".join(outside) or "all inside"})
    return out
