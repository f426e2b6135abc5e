import pytest
from pydantic import ValidationError

from ardflow.ardcore.errors import ModelError
from ardflow.ardcore.model.library import BUILTINS, builtin
from ardflow.ardcore.model.declaration import ModelSpec


def base(**kw):
    d = dict(name="m", states=["x"], drift={"x": "-k*x"}, diffusion={"x": "s"},
             observations=[{"column": "y", "expr": "x", "noise_std": 0.1}], parameters=["k", "s"])
    d.update(kw)
    return d


def test_every_builtin_parses_and_differentiates():
    for name in BUILTINS:
        s = builtin(name)
        sm = s.sym
        assert len(sm.drift) == len(s.states)
        assert sm.jacobian.shape == (len(s.states), len(s.states))


def test_sign_derivative_is_zero_in_jacobian():
    sm = builtin("M2").sym
    assert all("DiracDelta" not in str(e) for e in sm.jacobian)
    # d(dtheta')/d(dtheta) = c4 exactly (the Coulomb term contributes nothing)
    assert float(sm.jacobian[1, 1]) == pytest.approx(-7.275e-03)


@pytest.mark.parametrize("kw,msg", [
    (dict(drift={}), "no equation for state 'x'"),
    (dict(diffusion={"q": "s"}), "'q' is not a state"),
    (dict(parameters=["k", "s", "k"]), "declared twice"),
    (dict(parameters=["k", "sin"]), "reserved"),
    (dict(fixed={"zz": 0.0}), "'zz' is not a parameter"),
    (dict(constants={"c": float("nan")}), "finite"),
    (dict(states=["1x"]), "pattern"),
])
def test_bad_declarations_name_the_field(kw, msg):
    with pytest.raises(ValidationError) as ei:
        ModelSpec(**base(**kw))
    assert msg in str(ei.value)


def test_bad_expression_names_model_and_field():
    with pytest.raises(ModelError) as ei:
        ModelSpec(**base(drift={"x": "-k*x + open(1)"})).sym
    assert "drift['x']" in str(ei.value) and "open" in str(ei.value)


def test_fixed_parameter_leaves_phi():
    s = builtin("M2").with_fixed(a5=0.0, a6=0.0)
    assert s.free_parameters == ["B", "a1", "a2", "a3", "a4", "sigma"]
    assert s.structure_hash() != builtin("M2").structure_hash()


def test_extra_fields_rejected():
    with pytest.raises(ValidationError):
        ModelSpec(**base(evil=1))


def test_a_copy_with_another_drift_compiles_its_own_kernel():
    """model_copy(update=...) after the symbolic model was built must not reuse it (the copy's kernel would be
    the original's, cached under the copy's structure hash)."""
    import numpy as np

    from ardflow.ardcore.likelihood.ekf import compile_model
    from ardflow.ardcore.model.library import builtin

    spec = builtin("forced_linear_oscillator")
    assert spec.sym is not None  # built and cached on the original
    d = dict(spec.drift)
    v = [s for s in spec.states if s != d[spec.states[0]]][0]
    d[v] = f"({d[v]}) + kx*w"
    copy = spec.model_copy(update={"name": "copy_kx", "drift": d, "inputs": list(spec.inputs) + ["w"],
                                   "parameters": list(spec.parameters) + ["kx"]})
    cm = compile_model(copy)
    assert "kx" in cm.param_names
    t = np.arange(200) * 0.01
    U = np.column_stack([np.zeros((200, len(spec.inputs))), np.ones(200)])
    phi = {p: 1.0 for p in copy.free_parameters}
    _, H0 = cm.simulate({**phi, "kx": 0.0}, t, inputs=U, nsub=1, noise=False)
    _, H1 = cm.simulate({**phi, "kx": 5.0}, t, inputs=U, nsub=1, noise=False)
    assert np.abs(H1 - H0).max() > 1e-3
