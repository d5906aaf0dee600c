"""Which parts a registration check could not tell a new part from (``look_alikes.confused``)."""

from __future__ import annotations

from service.engine.look_alikes import confused


def check(render: str, label: str, runner_up: str | None = None, fit: float = 0.0) -> dict:
    return {"render": render, "label": label, "runner_up": runner_up, "runner_up_fit": fit}


def test_one_view_in_four_answered_as_another_part_makes_it_a_look_alike():
    # random-250's check on the report's gallery: one view of four answered as random-075,
    # which /detect then matched on random-075's points (docs/decisions.md#look-alike-parts)
    checks = [check("full", "random-250")] + [check("view", "random-250")] * 2
    assert confused("random-250", checks + [check("view", "random-075")]) == ["random-075"]
    assert confused("random-250", checks + [check("view", "random-250")]) == []
    fitted = check("full", "random-250", runner_up="random-075", fit=0.95)
    assert confused("random-250", [fitted] + checks[1:]) == ["random-075"]
    low = check("full", "random-250", runner_up="random-075", fit=0.5)
    assert confused("random-250", [low] + checks[1:]) == []
