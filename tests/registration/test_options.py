"""The registration's options: groups checked when made, flat names for the command line and the
API, and both surfaces derived from the same declarations."""

from __future__ import annotations

import dataclasses

import pytest

from vehicle_pose import RegistrationOptions
from vehicle_pose.cli import build_parser, options_from_args
from vehicle_pose.registration.options import Budgets, Pyramid, Search, Terms


def test_groups_hold_their_options_and_flat_names_reach_them() -> None:
    options = RegistrationOptions(budgets=Budgets(max_evaluations=150), terms=Terms(edge_weight=0.0))
    assert options.budgets.max_evaluations == 150 and options.terms.edge_weight == 0.0
    flat = RegistrationOptions.from_flat(max_evaluations=150, edge_weight=0.0, loss="invariant")
    assert flat == options.replace(loss="invariant")
    assert flat.flat()["max_evaluations"] == 150 and flat.flat()["loss"] == "invariant"
    assert RegistrationOptions.from_flat(RegistrationOptions().flat()) == RegistrationOptions()


def test_json_lists_become_tuples() -> None:
    options = RegistrationOptions.from_flat({"focal_starts": [0.5, 2.0], "region_borders": [[0.1, 0.1]]})
    assert options.probes.focal_starts == (0.5, 2.0) and options.search.region_borders == ((0.1, 0.1),)


@pytest.mark.parametrize(
    ("make", "words"),
    [
        (lambda: RegistrationOptions(loss="nope"), "unknown loss 'nope'; choose one of invariant"),
        (lambda: Budgets(max_evaluations=10), "max_evaluations must be in [20, 5000]"),
        (lambda: Budgets(max_evaluations=1.5), "max_evaluations must be a whole number"),
        (lambda: Pyramid(coarse_to_fine=1), "coarse_to_fine must be true or false"),
        (lambda: Terms(edge_weight=float("inf")), "edge_weight must be a finite number"),
        (lambda: Terms(box_shortfall=-0.1), "box_shortfall must be in [0.0, 1.0]"),
        (lambda: Search(refine_optimizer="bfgs"), "unknown refine_optimizer 'bfgs'"),
        (lambda: Search(region_borders=((0.1, 0.6),)), "region_borders must be in [0.0, 0.49]"),
        (lambda: RegistrationOptions.from_flat(no_such_option=1), "unknown option 'no_such_option'"),
        (lambda: RegistrationOptions(pyramid=Budgets()), "pyramid must be a Pyramid"),
    ],
)
def test_a_bad_option_is_a_value_error_naming_it(make, words) -> None:
    with pytest.raises(ValueError, match=words.replace("[", r"\[").replace("]", r"\]")):
        make()


def test_none_only_where_an_option_allows_it() -> None:
    assert Terms(box_shortfall=None).box_shortfall is None
    with pytest.raises(ValueError, match="edge_weight may not be None"):
        Terms(edge_weight=None)


def test_every_public_option_is_a_cli_flag_and_an_api_field() -> None:
    from app.schemas import RegistrationOptionsIn

    public = [name for name, _, spec in RegistrationOptions.specs() if spec.public]
    assert {"loss", "max_evaluations", "edge_weight", "focal_starts", "starts"} <= set(public)
    parsed = vars(build_parser().parse_args(["register", "p.jpg", "--model", "sedan", "--out", "r.json"]))
    assert set(public) <= set(parsed) and all(parsed[name] is None for name in public)
    assert set(RegistrationOptionsIn.model_fields) == set(public)
    schema = RegistrationOptionsIn.model_json_schema()["properties"]
    assert schema["max_evaluations"]["anyOf"][0]["maximum"] == 5000
    assert "invariant-parts" in schema["loss"]["anyOf"][0]["enum"]


def test_cli_flags_set_what_they_say() -> None:
    args = build_parser().parse_args(["register", "p.jpg", "--model", "sedan", "--out", "r.json", "--no-grabcut",
                                      "--single-level", "--no-focal-probes", "--color", "--edge-weight", "0",
                                      "--max-evaluations", "150"])
    options = options_from_args(args)
    assert not options.segmentation.grabcut and not options.pyramid.coarse_to_fine and options.color
    assert options.probes.focal_starts == () and options.terms.edge_weight == 0.0
    assert options.budgets.max_evaluations == 150
    assert dataclasses.replace(options, color=False).segmentation == options.segmentation
