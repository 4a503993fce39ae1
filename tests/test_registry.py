"""The registries of losses, optimisers and search coordinates: every declared name resolves to
a factory of its implementing module, and a bad name gets a ValueError that lists the choices."""

from __future__ import annotations

import pytest

from vehicle_pose.registry import LOSSES, OPTIMIZERS, PARAMETRIZATIONS, Registry


@pytest.mark.parametrize("registry", [LOSSES, OPTIMIZERS, PARAMETRIZATIONS], ids=lambda r: r.kind)
def test_every_declared_name_has_a_factory(registry: Registry) -> None:
    for name in registry:
        assert callable(registry.get(name))


def test_an_unknown_name_lists_the_choices() -> None:
    with pytest.raises(ValueError, match="unknown optimizer 'bfgs'; choose one of nelder-mead, powell, cma-es"):
        OPTIMIZERS.get("bfgs")
    assert "bfgs" not in OPTIMIZERS and "powell" in OPTIMIZERS


def test_only_declared_names_can_be_registered() -> None:
    registry: Registry = Registry("thing", ("a",), "vehicle_pose.registry")
    with pytest.raises(ValueError, match="not a declared thing"):
        registry.register("b")
    with pytest.raises(LookupError, match="registers no thing 'a'"):
        registry.get("a")
