"""The run file's seal: every edit of every stored table and column is refused by the gate, naming what changed;
a file from before seals reads as unsealed and is sealed at its next write."""

from __future__ import annotations

import dataclasses
import json
import shutil
import sqlite3
from pathlib import Path

import pytest
from deploy_runs import FINGERPRINT, altered_copy, make_run

from npp_ros.deployment.gate import Acceptance, GateRefusal, load_deployment
from npp_ros.run.records import RunFileError
from npp_ros.run.seal import SEAL_TABLE, part_name
from npp_ros.run.store import RunStore

ACCEPT = Acceptance(model_fingerprint=FINGERPRINT)
# Any value changed: text gets a character, a number 1 more, a NULL becomes 1. The last row, so that a key
# column moved by 1 collides with no other row.
CHANGE = (
    'UPDATE {table} SET "{column}" = CASE WHEN typeof("{column}") = \'text\' THEN "{column}" || \' \' '
    'WHEN "{column}" IS NULL THEN 1 ELSE "{column}" + 1 END WHERE rowid = (SELECT MAX(rowid) FROM {table})'
)


@pytest.fixture(scope="module")
def good(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_run(tmp_path_factory.mktemp("seal") / "good")


def stored_columns(run: Path) -> list[tuple[str, str]]:
    """(table, column) for every meta key and every column of the data tables the run file holds."""
    with sqlite3.connect(run / "run.sqlite") as conn:
        found = [("meta", str(key)) for (key,) in conn.execute("SELECT key FROM meta ORDER BY key")]
        for table in ("trajectories", "points", "episodes"):
            found += [(table, str(row[1])) for row in conn.execute(f"PRAGMA table_info({table})")]
    return found


def test_a_fresh_run_is_sealed_and_passes(good: Path) -> None:
    with RunStore.open(good / "run.sqlite") as store:
        seal = store.check_seal()
    assert seal.sealed and not seal.mismatches and len(seal.digest) == 64
    assert load_deployment(good, ACCEPT).seal.digest == seal.digest


def test_every_column_of_every_table_edited_is_refused_naming_it(good: Path, tmp_path: Path) -> None:
    columns = stored_columns(good)
    assert len(columns) > 40 and ("meta", "epsilon") in columns and ("points", "q") in columns
    for k, (table, column) in enumerate(columns):
        if table == "meta":
            edit = ("UPDATE meta SET value = value || ' ' WHERE key = ?", (column,))
        else:
            edit = (CHANGE.format(table=table, column=column), ())
        folder = altered_copy(good, tmp_path / f"{k}", edit)
        with pytest.raises(GateRefusal, match="altered") as refusal:
            load_deployment(folder, ACCEPT)
        assert f"{part_name(table, column)}" in str(refusal.value), (table, column, str(refusal.value))
        assert "no longer matches its seal" in str(refusal.value)
        shutil.rmtree(folder)


def test_epsilon_edited_in_both_the_metadata_and_the_certificate_is_refused(good: Path, tmp_path: Path) -> None:
    """The replay of the log gives the same decisions for a looser epsilon: only the seal tells."""
    with sqlite3.connect(good / "run.sqlite") as conn:
        record = json.loads(conn.execute("SELECT value FROM meta WHERE key = 'certificate'").fetchone()[0])
    record["epsilon"] = 3.0
    both = altered_copy(
        good, tmp_path / "both", ("UPDATE meta SET value = '3.0' WHERE key = 'epsilon'", ()),
        ("UPDATE meta SET value = ? WHERE key = 'certificate'", (json.dumps(record),)),
    )  # fmt: skip
    with pytest.raises(GateRefusal, match="meta 'certificate', meta 'epsilon' changed after the run wrote it"):
        load_deployment(both, ACCEPT)


def test_rows_removed_or_added_and_the_seal_itself_edited_are_refused(good: Path, tmp_path: Path) -> None:
    cases = {
        "DELETE FROM episodes WHERE episode = (SELECT MAX(episode) FROM episodes)": "episodes.episode",
        "DELETE FROM points WHERE step = 3 AND trajectory = 0": "points.step",
        "DELETE FROM meta WHERE key = 'certificate'": "meta 'certificate' (removed)",
        "INSERT INTO meta VALUES ('note', 'x')": "meta 'note' (not sealed: added after the run)",
        "ALTER TABLE episodes ADD COLUMN extra TEXT": "episodes.extra (not sealed",
        f"UPDATE {SEAL_TABLE} SET sha256 = '00' WHERE part = 'episodes.v_lb'": "episodes.v_lb",
        f"UPDATE {SEAL_TABLE} SET sha256 = '00' WHERE part = 'run'": "the seal's own digest",
    }
    for k, (sql, named) in enumerate(cases.items()):
        with pytest.raises(GateRefusal, match="altered") as refusal:
            load_deployment(altered_copy(good, tmp_path / str(k), (sql, ())), ACCEPT)
        assert named in str(refusal.value), (sql, str(refusal.value))


def test_a_file_without_a_seal_is_refused_unless_allowed_by_name_and_is_sealed_at_its_next_write(
    good: Path, tmp_path: Path
) -> None:
    """Dropping the seal table is an edit too: the gate refuses the file unless the operator allows unsealed files,
    and says so in its provenance while it runs."""
    old = altered_copy(good, tmp_path / "old", (f"DROP TABLE {SEAL_TABLE}", ()))
    with pytest.raises(GateRefusal, match=r"has no seal, so nothing shows it unchanged since its run.*allow_unsealed"):
        load_deployment(old, ACCEPT)
    with pytest.raises(GateRefusal, match="has no seal"):  # override_gate is no way round it
        load_deployment(old, dataclasses.replace(ACCEPT, override=True))
    deployment = load_deployment(old, dataclasses.replace(ACCEPT, allow_unsealed=True))
    assert not deployment.seal.sealed and "UNSEALED" in deployment.seal.describe()
    with RunStore.open(old / "run.sqlite") as store:
        certificate = store.certificate()
        assert certificate is not None
        store.set_certificate(certificate)  # any write
    with RunStore.open(old / "run.sqlite") as store:
        seal = store.check_seal()
    assert seal.sealed and not seal.mismatches
    with RunStore.open(good / "run.sqlite") as store:
        assert seal.digest == store.check_seal().digest  # the same content, the same digest


def test_the_seal_is_written_in_each_commit_and_extended_trajectory_by_trajectory(tmp_path: Path) -> None:
    """A run stopped early and resumed ends with the seal of the file as it stands, as an uninterrupted run."""
    short = make_run(tmp_path / "short", max_episodes=5)
    with RunStore.open(short / "run.sqlite") as store:
        first = store.check_seal()
    resumed = make_run(short, max_episodes=40)
    with RunStore.open(resumed / "run.sqlite") as store:
        after = store.check_seal()
    assert first.sealed and after.sealed and not after.mismatches and after.digest != first.digest
    whole = make_run(tmp_path / "whole", max_episodes=40)
    with sqlite3.connect(whole / "run.sqlite") as a, sqlite3.connect(resumed / "run.sqlite") as b:
        points = [dict(c.execute(f"SELECT part, sha256 FROM {SEAL_TABLE} WHERE part LIKE 'points.%'")) for c in (a, b)]
    assert points[0] == points[1]  # the chains extended commit by commit equal the chains computed at once


def test_a_run_whose_file_was_edited_since_it_sealed_it_does_not_resume_or_write(tmp_path: Path) -> None:
    """An edit between two writes would otherwise be sealed over as the run's own by the next one."""
    stopped = make_run(tmp_path / "stopped", max_episodes=5)
    edited = altered_copy(stopped, tmp_path / "edited", ("UPDATE episodes SET v_lb = v_lb + 1 WHERE episode = 2", ()))
    before = (edited / "run.sqlite").read_bytes()
    with pytest.raises(RunFileError, match=r"no longer holds what its run sealed \(episodes.v_lb changed since\)"):
        make_run(edited, max_episodes=40)
    with RunStore.open(edited / "run.sqlite") as store:
        with pytest.raises(RunFileError, match="left untouched, and no run resumes from it"):
            store.set_certificate({"edited": True})
    assert (edited / "run.sqlite").read_bytes() == before
    resumed = make_run(altered_copy(stopped, tmp_path / "intact"), max_episodes=40)  # an intact copy resumes
    with RunStore.open(resumed / "run.sqlite") as store:
        assert not store.check_seal().mismatches and len(store.episodes()) > 5
