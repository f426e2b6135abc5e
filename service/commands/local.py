"""``ardflow`` commands that work on models, data and examples on this machine (no cluster)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def parse_assignments(items: list[str] | None, what: str) -> dict[str, str]:
    from ardflow.ardcore.errors import SpecError

    out = {}
    for it in items or []:
        if "=" not in it:
            raise SpecError(f"{what}: expected NAME=VALUE, got {it!r}")
        k, v = it.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def _floats(d: dict[str, str], what: str) -> dict[str, float]:
    from ardflow.ardcore.errors import SpecError

    out = {}
    for k, v in d.items():
        try:
            x = float(v)
        except ValueError:
            raise SpecError(f"{what} {k}: {v!r} is not a number") from None
        if not np.isfinite(x):
            raise SpecError(f"{what} {k}: must be finite, got {v!r}")
        out[k] = x
    return out


def _load_model(name_or_file: str):
    from ardflow.ardcore.errors import ModelError, did_you_mean
    from ardflow.ardcore.model.library import BUILTINS, builtin
    from ardflow.ardcore.model.declaration import ModelSpec

    if name_or_file in BUILTINS:
        return builtin(name_or_file)
    p = Path(name_or_file)
    if p.suffix == ".json" and p.exists():
        try:
            return ModelSpec.model_validate_json(p.read_text())
        except ValueError as exc:
            raise ModelError(f"{p}: {exc}") from None
    raise ModelError(f"unknown model {name_or_file!r}{did_you_mean(name_or_file, BUILTINS)}: give a built-in "
                     f"name ({', '.join(BUILTINS)}) or a model JSON file")


def _write_sidecar(path: Path, meta: dict) -> None:
    meta = {k: v for k, v in meta.items() if k != "theta_clean"}
    path.with_suffix(".json").write_text(json.dumps(meta, indent=2, default=float))


def cmd_simulate(a) -> int:
    from ardflow.ardcore.errors import SpecError
    from ardflow.ardcore.likelihood.simulate import simulate_model, simulate_reference

    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if a.model == "reference":
        ds = simulate_reference(a.seed)
    else:
        spec = _load_model(a.model)
        params = _floats(parse_assignments(a.param, "--param"), "parameter")
        missing = [p for p in spec.free_parameters if p not in params]
        if missing:
            raise SpecError(f"--param: no value for {missing[0]!r} (parameters: {spec.free_parameters})")
        if a.n < 10 or not (a.dt > 0):
            raise SpecError("--n must be >= 10 and --dt > 0")
        t = np.arange(a.n) * a.dt
        inputs = {}
        rng = np.random.default_rng(a.seed + 1_000_003)
        for c in spec.inputs:
            from ardflow.ardcore.likelihood.simulate import lowpass

            inputs[c] = a.input_std * lowpass(rng.standard_normal(a.n), 1.0 / a.dt, 0.2 / a.dt) * np.sqrt(5.0)
        ds = simulate_model(spec, params, t, a.seed, nsub=a.nsub, inputs=inputs)
    ds.to_csv(out)
    _write_sidecar(out, ds.meta)
    print(f"wrote {out} ({len(ds)} rows) and {out.with_suffix('.json')}")
    return 0


def cmd_loglik(a) -> int:
    from ardflow.ardcore.likelihood.ekf import compile_model
    from ardflow.ardcore.errors import SpecError

    ds = _read_data(a)
    spec = _load_model(a.model)
    params = _floats(parse_assignments(a.param, "--param"), "parameter")
    missing = [p for p in spec.free_parameters if p not in params]
    if missing:
        raise SpecError(f"--param: no value for {missing[0]!r} (parameters: {spec.free_parameters})")
    unknown = [p for p in params if p not in spec.free_parameters]
    if unknown:
        raise SpecError(f"--param: {unknown[0]!r} is not a free parameter of {spec.name}")
    cm = compile_model(spec)
    ll = cm.loglik(params, ds, substeps=a.substeps)
    print(json.dumps({"model": spec.name, "loglik": ll, "substeps": a.substeps or spec.substeps}))
    return 0


def _read_data(a):
    from ardflow.ardcore.data import read_dataset

    rename = parse_assignments(getattr(a, "rename", None), "--rename")
    return read_dataset(a.data, fs=getattr(a, "fs", None), rename=rename)


def cmd_data(a) -> int:
    from ardflow.ardcore.data import read_columns

    if a.action == "check":
        ds = _read_data(a)
        info = {"rows": len(ds), "t0": float(ds.t[0]), "t1": float(ds.t[-1]),
                "columns": {k: {"nan": int(np.isnan(v).sum()), "min": float(np.nanmin(v)), "max": float(np.nanmax(v))}
                            for k, v in ds.columns.items()}}
        print(json.dumps(info, indent=2))
    else:  # convert
        cols = read_columns(a.data)
        from ardflow.ardcore.data import Dataset

        rename = parse_assignments(a.rename, "--rename")
        for o, n in rename.items():
            cols[n] = cols.pop(o)
        t = cols.pop("t") if "t" in cols else np.arange(len(next(iter(cols.values())))) / (a.fs or 1.0)
        ds = Dataset(t, cols, {"source": str(a.data)})
        ds.to_csv(a.out)
        print(f"wrote {a.out} ({len(ds)} rows, columns t, {', '.join(cols)})")
    return 0


def cmd_models(a) -> int:
    from ardflow.ardcore.model.library import BUILTINS, builtin

    if a.name:
        print(_load_model(a.name).model_dump_json(indent=2))
    else:
        for n in BUILTINS:
            s = builtin(n)
            print(f"{n:26s} {s.description}")
    return 0


# the examples folder: beside the source folders in a checkout, package data (ardflow/examples) in a wheel
EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def cmd_example(a) -> int:
    """List the example study specs, or write one out to start your own study from."""
    from ardflow.ardcore.errors import did_you_mean

    names = sorted(p.stem for p in EXAMPLES.glob("*.json"))
    if not a.name:
        for n in names:
            desc = json.loads((EXAMPLES / f"{n}.json").read_text()).get("description", "")
            print(f"{n:22s} {desc[:90]}")
        return 0
    if a.name not in names:
        raise SystemExit(f"error: no example {a.name!r}{did_you_mean(a.name, names)} (examples: {', '.join(names)})")
    text = (EXAMPLES / f"{a.name}.json").read_text()
    if a.out:
        Path(a.out).write_text(text)
        print(f"wrote {a.out}")
    else:
        print(text)
    return 0


SETTINGS_SECTIONS = {"sampler": "ardflow.ardcore.sampling.config:SamplerConfig",
                     "maximiser": "ardflow.ardcore.selection.maximiser:MaximiserConfig"}


def settings_table(model) -> list[tuple[str, str, str, str]]:
    """(field, default, bounds, meaning) for every field of a settings model: read from the one declaration
    (the pydantic fields and the numpydoc ``Attributes`` of its docstring), so nothing is written twice."""
    import inspect

    meaning: dict[str, list[str]] = {}
    cur: list[str] = []
    for line in inspect.cleandoc(model.__doc__ or "").splitlines():
        if " : " in line and not line.startswith(" "):
            cur = [n.strip() for n in line.split(" : ")[0].split(",")]
            for n in cur:
                meaning[n] = []
        elif line.startswith(" ") and cur:
            for n in cur:
                meaning[n].append(line.strip())
    props = model.model_json_schema()["properties"]
    rows = []
    for name, f in model.model_fields.items():
        p = props.get(name, {})
        bounds = [f"{op} {p[k]:g}" for k, op in (("exclusiveMinimum", ">"), ("minimum", ">="),
                                                   ("exclusiveMaximum", "<"), ("maximum", "<="))
                  if k in p]
        bounds += [" | ".join(map(repr, p["enum"]))] if "enum" in p else []
        text = " ".join(meaning.get(name, [])) or (f.description or "")
        default = f"{f.default:g}" if isinstance(f.default, float) else repr(f.default)
        rows.append((name, default, ", ".join(bounds), text))
    return rows


def cmd_settings(a) -> int:
    """Print a spec section's settings: field, default, bounds and meaning."""
    from importlib import import_module

    for section in [a.section] if a.section else list(SETTINGS_SECTIONS):
        mod, cls = SETTINGS_SECTIONS[section].split(":")
        print(f"[{section}]")
        for name, default, bounds, text in settings_table(getattr(import_module(mod), cls)):
            print(f"  {name:20s} {default:>10s}  {bounds:22s} {text}")
        print()
    return 0
