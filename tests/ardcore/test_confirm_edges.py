"""Which shaped candidates a confirmation fits with their shape: a profile that climbs to the end of the range
where the effect becomes a simpler family is confirmed at the screen's shape; any other is fitted."""

import pytest

from ardflow.ardcore.loop.confirm import at_range_edge, fitted_effect
from ardflow.ardcore.effects.families import candidate_effects
from ardflow.ardcore.model.declaration import ModelSpec
from ardflow.ardcore.screening.screen import Screened


def _spec() -> ModelSpec:
    return ModelSpec(name="osc_edges", states=["y", "v"], inputs=["u"], drift={"y": "v", "v": "-k*y - c*v + b*u"},
                     diffusion={"v": "sigma"}, observations=[{"column": "y", "expr": "y", "noise_std": "0.01"}],
                     parameters=["k", "c", "b", "sigma"], initial_std={"y": 0.5, "v": 2.0})


def _library() -> dict:
    spec = _spec()
    effects = candidate_effects(spec, scales={"y": 1.0, "v": 3.0}, levels={"y": (-2.0, 0.0, 2.0), "v": (-6, 0, 6)})
    return {e.name: e for e in effects if e.shape and e.shape[0] != "f"}


def _screened(e, value):
    return Screened(e.at(value), "v", 50.0, 50.0, [0.1], [1.0], source=e, shape_value=value)


@pytest.mark.parametrize("name,end", [("dry_friction(v)", "high"), ("saturation(y)", "high"),
                                      ("free_play(y)", "low"), ("sine_stiffness(y)", "high")])
def test_a_profile_at_the_degenerate_end_is_confirmed_at_the_screens_shape(name, end):
    e = _library()[name]
    assert e.degenerate == end
    _, lo, hi = e.shape
    edge, other = (hi, lo) if end == "high" else (lo, hi)
    eff, prior = fitted_effect(_spec(), _screened(e, edge), "v")
    assert prior == {} and eff.name == e.at(edge).name and at_range_edge(e, edge) == end
    # at the other end, and inside the range, the shape is fitted with the coefficients
    for v in (other, (lo * hi) ** 0.5):
        eff, prior = fitted_effect(_spec(), _screened(e, v), "v")
        assert len(prior) == 1 and eff.shape_parameter in prior, (name, v)


def test_a_shape_without_a_degenerate_end_is_fitted_at_either_edge():
    contacts = [e for n, e in _library().items() if n.startswith("contact")]
    assert contacts and all(not e.degenerate for e in contacts)
    for e in contacts:
        _, lo, hi = e.shape
        for v in (lo, hi):
            assert at_range_edge(e, v)
            eff, prior = fitted_effect(_spec(), _screened(e, v), "v")
            assert len(prior) == 1 and eff.shape_parameter in prior
