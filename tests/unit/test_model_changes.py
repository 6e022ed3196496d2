"""Changes of a run's model: the term check, replaying a run's changes on a
configuration, and the ``model_changes`` table as the store and the
dashboard's read-only reader give it back."""

from __future__ import annotations

import math
import sqlite3
from pathlib import Path

import pytest

from afmdrift.config import ModelConfig, PhysicsConfig
from afmdrift.dashboard import RunReader
from afmdrift.errors import ConfigError
from afmdrift.runs import ModelChange, RunStore, change_terms, effective_model


def _model(*terms: str, predictor: str = "physics") -> ModelConfig:
    return ModelConfig(predictor=predictor, physics=PhysicsConfig(terms=list(terms)))


def _change(command: str, term: str | None, seq: int = 3) -> ModelChange:
    return ModelChange(
        seq=seq, t_s=math.nan, wall_s=1.0, command=command, term=term, predictor="physics",
        terms_before=None, terms_after=None,
    )  # fmt: skip


def test_change_terms_adds_and_removes_and_builds_the_predictor() -> None:
    model, predictor = change_terms(_model("trend"), "add_term", " channel:pressure_hpa ")
    assert model.physics.terms == ["trend", "channel:pressure_hpa"]
    assert [t.name for t in predictor.terms] == ["trend", "channel:pressure_hpa"]  # type: ignore[attr-defined]
    model, _ = change_terms(model, "remove_term", "trend")
    assert model.physics.terms == ["channel:pressure_hpa"]


@pytest.mark.parametrize(
    ("model", "command", "term", "why"),
    [
        (_model("trend"), "add_term", "trend", "add_term: 'trend' is already a term"),
        (_model("trend"), "add_term", "", "needs a term"),
        (
            _model("trend"),
            "add_term",
            "no_such",
            r"add_term 'no_such': model.physics.terms: unknown",
        ),
        (_model("trend"), "add_term", "event:door:slow", "unknown option 'slow'"),
        (_model("trend", "creep"), "remove_term", "humidity", "'humidity' is not a term"),
        (_model("trend"), "remove_term", "trend", "the model's only term"),
        (_model("trend", predictor="kalman"), "add_term", "humidity", "'kalman', which has no"),
        (_model("trend"), "reload_model", "humidity", "not a term command"),
    ],
)
def test_change_terms_refuses_naming_why(
    model: ModelConfig, command: str, term: str, why: str
) -> None:
    with pytest.raises(ConfigError, match=why):
        change_terms(model, command, term)


def test_effective_model_replays_the_changes_after_the_last_reload() -> None:
    """Regression guard: a restarted daemon must apply the run's term changes
    to its configuration, from the last reload_model (which took a file's
    terms) on, and skip one the configuration makes meaningless."""
    changes = [
        _change("add_term", "humidity"),
        _change("reload_model", None),
        _change("add_term", "creep"),
        _change("add_term", "warmup"),  # the configuration has it already: skipped
        _change("remove_term", "trend"),
    ]
    model = effective_model(_model("trend", "warmup"), changes)
    assert model.physics.terms == ["warmup", "creep"]
    assert effective_model(_model("trend"), []) == _model("trend")


def test_model_changes_round_trip_through_the_store_and_the_reader(tmp_path: Path) -> None:
    change = ModelChange(
        seq=12, t_s=384.5, wall_s=1.7e9, command="add_term", term="humidity",
        predictor="physics", terms_before=("trend",), terms_after=("trend", "humidity"),
        handover_until_s=390.0, step_bound_nm=0.5,
    )  # fmt: skip
    early = ModelChange(
        seq=-1, t_s=math.nan, wall_s=1.7e9, command="reload_model", term=None,
        predictor="kalman", terms_before=("trend",), terms_after=None,
    )  # fmt: skip
    with RunStore(tmp_path) as store:
        assert store.model_changes() == []
        store.add_model_change(early)
        store.add_model_change(change)
        got = store.model_changes()
    assert got[1] == change
    assert got[0].seq == -1
    assert math.isnan(got[0].t_s)
    assert got[0].terms_after is None
    with RunReader(tmp_path) as reader:
        assert reader.model_changes()[1] == change


def test_reader_of_a_store_without_the_table_sees_no_changes(tmp_path: Path) -> None:
    """A store written before the table existed (same schema version) is read
    as a run whose model never changed, without writing to it."""
    with RunStore(tmp_path):
        pass
    db = sqlite3.connect(tmp_path / "run.sqlite")
    db.execute("DROP TABLE model_changes")
    db.commit()
    db.close()
    with RunReader(tmp_path) as reader:
        assert reader.model_changes() == []
