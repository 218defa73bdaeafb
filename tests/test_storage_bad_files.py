"""Damaged and foreign run files, generated with hypothesis: a precise RunFileError, and not one byte changed.

Truncated at any length, another format version, dimensions that are not the task's, metadata that lies
about the columns: each is refused when opened or loaded, and the file on disk is left exactly as it was
(no journal either). The cases tried are counted and printed.
"""

from __future__ import annotations

import hashlib
import re
import shutil
import sqlite3
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_storage import META, fill

from npp_ros.run.records import RunFileError, RunMetadata
from npp_ros.run.store import READABLE_VERSIONS, RunStore

FILES = settings(max_examples=25, deadline=None, derandomize=True, database=None)
tried: Counter[str] = Counter()


@pytest.fixture(scope="module", autouse=True)
def report_counts() -> Iterator[None]:
    yield
    print("\nrun-file cases tried: " + ", ".join(f"{k} {v}" for k, v in sorted(tried.items())))


@pytest.fixture(scope="module")
def good_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("good") / "run.sqlite"
    with RunStore.create(path, META) as store:
        fill(store, 20)
    return path


def copy(good: Path, tmp: pytest.TempPathFactory) -> Path:
    path = tmp.mktemp("case") / "run.sqlite"
    shutil.copyfile(good, path)
    return path


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def assert_untouched(path: Path, before: str) -> None:
    assert digest(path) == before, "a refused file was modified"
    assert sorted(p.name for p in path.parent.iterdir()) == ["run.sqlite"], "a journal or other file was left"


def open_and_load(path: Path) -> None:
    with RunStore.open(path) as store:
        store.load_dataset()


@FILES
@given(keep=st.integers(0, 10**9))
def test_truncated_files_are_refused_unchanged(good_file: Path, tmp_path_factory, keep: int) -> None:
    path = copy(good_file, tmp_path_factory)
    size = path.stat().st_size
    with path.open("r+b") as fh:
        fh.truncate(keep % size)  # anything from empty to one byte short
    before = digest(path)
    with pytest.raises(RunFileError, match=r"damaged|not a readable|cannot read|not an npp_ros run file"):
        open_and_load(path)
    assert_untouched(path, before)
    tried["truncated"] += 1


@FILES
@given(
    version=st.text(st.characters(blacklist_categories=("Cs",)), max_size=12).filter(
        lambda v: v not in [str(known) for known in READABLE_VERSIONS]
    )
)
def test_other_versions_are_refused_unchanged(good_file: Path, tmp_path_factory, version: str) -> None:
    path = copy(good_file, tmp_path_factory)
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE meta SET value = ? WHERE key = 'format_version'", (version,))
    conn.close()
    before = digest(path)
    readable = ", ".join(map(str, READABLE_VERSIONS))
    expected = f"has format version {version}, this npp_ros reads versions {readable}"
    with pytest.raises(RunFileError, match=re.escape(expected)):
        open_and_load(path)
    assert_untouched(path, before)
    tried["other version"] += 1


@FILES
@given(dims=st.tuples(st.integers(1, 24), st.integers(1, 6)).filter(lambda d: d != (4, 1)))
def test_files_for_other_dimensions_are_refused_unchanged(tmp_path_factory, dims: tuple[int, int]) -> None:
    """A file made for other state/action sizes, resumed as lqr_2_1 (4 and 1): the run refuses it."""
    n, m = dims
    path = tmp_path_factory.mktemp("dims") / "run.sqlite"
    RunStore.create(path, RunMetadata(**(vars(META) | {"state_dim": n, "action_dim": m}))).close()
    before = digest(path)
    field = "state_dim" if n != 4 else "action_dim"
    expected = f"{field}: file has {n if n != 4 else m}, this run asks for {4 if n != 4 else 1}"
    with pytest.raises(RunFileError, match=re.escape(expected)):
        RunStore.open_or_create(path, META)
    assert_untouched(path, before)
    tried["other dimensions"] += 1


@FILES
@given(claimed=st.tuples(st.integers(1, 24), st.integers(1, 6)).filter(lambda d: d != (4, 1)))
def test_metadata_that_lies_about_the_columns_fails_to_load_unchanged(
    good_file: Path, tmp_path_factory, claimed: tuple[int, int]
) -> None:
    """The meta table says other dimensions than the stored columns: loading stops, it never misreads."""
    path = copy(good_file, tmp_path_factory)
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE meta SET value = ? WHERE key = 'state_dim'", (str(claimed[0]),))
        conn.execute("UPDATE meta SET value = ? WHERE key = 'action_dim'", (str(claimed[1]),))
    conn.close()
    before = digest(path)
    with pytest.raises(RunFileError, match=r"cannot read the dataset|fails its SHA-256 check|invalid trajectory"):
        open_and_load(path)
    assert_untouched(path, before)
    tried["lying metadata"] += 1


@pytest.mark.parametrize("key", ["task", "horizon", "epsilon"])
def test_a_missing_metadata_key_is_named(good_file: Path, tmp_path_factory: pytest.TempPathFactory, key: str) -> None:
    """A hand-edited file without one of its metadata keys: readers get a RunFileError that names the key."""
    path = copy(good_file, tmp_path_factory)
    conn = sqlite3.connect(path)
    with conn:
        conn.execute("DELETE FROM meta WHERE key = ?", (key,))
    conn.close()
    before = digest(path)
    with RunStore.open(path) as store:
        assert not hasattr(store.metadata, key)
        with pytest.raises(RunFileError, match=f"metadata has no '{key}'"):
            getattr(store.metadata, key)
    assert_untouched(path, before)
    tried["metadata key missing"] += 1
