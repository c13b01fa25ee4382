"""The contracts are written once, in ``harness.core.contracts``, and stay small: what a newcomer
implements to add a plant, a learner, a model, a controller or a reference."""

from __future__ import annotations

import inspect
import typing

import pytest

import learners
from harness.core import contracts
from harness.references import CourseReference

PROTOCOLS = [
    value
    for value in vars(contracts).values()
    if inspect.isclass(value)
    and getattr(value, "_is_protocol", False)
    and value.__module__ == contracts.__name__
]


def own_members(protocol: type) -> set[str]:
    """The members a protocol adds to the protocols it extends."""
    members = typing._get_protocol_attrs  # type: ignore[attr-defined]
    bases = [base for base in protocol.__bases__ if base in PROTOCOLS]
    return set(members(protocol)).difference(*(members(base) for base in bases))


def test_every_contract_named_by_the_design_lives_in_core() -> None:
    names = {protocol.__name__ for protocol in PROTOCOLS}
    assert {"Plant", "Learner", "Model", "LiftedModel", "BilinearModel"} <= names
    assert {"LinearizableModel", "Controller", "Reference"} <= names
    assert contracts.Reference in CourseReference.__mro__  # refines it, does not restate it


@pytest.mark.parametrize("protocol", PROTOCOLS, ids=lambda protocol: protocol.__name__)
def test_each_contract_has_at_most_five_members_of_its_own(protocol: type) -> None:
    members = own_members(protocol)
    assert 1 <= len(members) <= 5, sorted(members)


def test_the_learner_abc_implements_the_contract_and_the_koopman_one_the_lifted_model() -> None:
    assert contracts.Learner in learners.Learner.__mro__
    assert contracts.RunLearner in learners.Learner.__mro__  # what a run asks of it besides
    assert contracts.LiftedModel in learners.KoopmanLearner.__mro__
    assert learners.KoopmanLearner.dynamics == "linear"
    # Implemented, not restated: the Koopman ABC declares none of the lifted model's members.
    restated = own_members(contracts.LiftedModel) & set(vars(learners.KoopmanLearner))
    assert not restated, restated
