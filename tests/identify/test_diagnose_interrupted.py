"""A diagnosis interrupted during its search rounds (`identify._diagnose.search`): what was
accepted before Ctrl-C is reported, marked; before the rounds, or when the state was left
half-way, the interruption propagates (nothing consistent to report)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

import identify._diagnose.search as search_module


def _options():
    return SimpleNamespace(max_effects=3, say=lambda msg: None)


def test_ctrl_c_in_a_round_ends_the_search_with_what_was_accepted(monkeypatch):
    state = SimpleNamespace(round=0, accepted=[])

    def one_accepted_then_interrupted(superset, held, options, structural, state, cands, signals):
        if state.round == 1:
            raise KeyboardInterrupt
        state.accepted.append("coulomb_friction:joint1")
        return True

    monkeypatch.setattr(search_module, "_round", one_accepted_then_interrupted)
    text = search_module._rounds(None, None, _options(), None, state, [], None)
    assert text == "interrupted (Ctrl-C) in round 2, after 1 cause(s) accepted; the search did not finish"
    assert state.accepted == ["coulomb_friction:joint1"]


def test_a_finished_search_is_not_marked(monkeypatch):
    monkeypatch.setattr(search_module, "_round", lambda *args: False)
    assert search_module._rounds(None, None, _options(), None, SimpleNamespace(round=0, accepted=[]), [], None) is None


def test_the_diagnosis_carries_the_interruption_or_propagates_it(monkeypatch):
    import dataclasses

    @dataclasses.dataclass
    class Diag:
        interrupted: object = None

    monkeypatch.setattr(search_module, "assemble", lambda **parts: Diag())
    assert search_module._assembled("stopped in round 2").interrupted == "stopped in round 2"
    assert search_module._assembled(None).interrupted is None

    def half_way(**parts):
        raise IndexError("a round's scores without its winner")

    monkeypatch.setattr(search_module, "assemble", half_way)
    with pytest.raises(KeyboardInterrupt):
        search_module._assembled("stopped in round 2")
    with pytest.raises(IndexError):  # (not interrupted: a real error stays one)
        search_module._assembled(None)
