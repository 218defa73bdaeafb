"""A robot's model as MJCF text: what npp-robot publishes on /robot_description, and its fingerprint.

The gate compares the robot's model fingerprint with the one the run recorded for its plant
(``Plant.model_sha256``, a SHA-256 over the compiled model's dynamics arrays). A robot that
describes itself in MJCF needs no operator to copy that fingerprint: :func:`mjcf_fingerprint`
compiles the text with MuJoCo and hashes it with the task plant's own code, so the two agree
exactly when the compiled dynamics do. :func:`model_mjcf` gives a plant's MJCF as one
self-contained text (includes inlined, numbers as the source wrote them: MuJoCo's own XML writer
rounds them to 6 digits, which changes the fingerprint). A model that loads files (a mesh, a texture: an
arm's links) names them by absolute path there, as MuJoCo resolves them from the model's folder: the
text then compiles wherever those files are at that path (the robot's host, a checkout at the same
place), as a URDF's meshes resolve only where their package is installed.
"""

from __future__ import annotations

import copy
import importlib
import os
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from npp_ros.run.read import checked_metadata, task_of
from npp_ros.run.records import RunFileError
from npp_ros.run.store import RUN_FILE, RunStore
from npp_ros.tasks.registry import Plant, UnknownTaskError


class DescriptionError(ValueError):
    """A robot description that does not compile as a MuJoCo model."""


def model_mjcf(plant: Plant) -> str | None:
    """The plant's model as one MJCF text that compiles alone; None for a plant that does not say where its
    model comes from (a plug-in's own plant)."""
    source = _source_of(plant)
    if source is None:
        return None
    text, read = source
    return inline_includes(text, read)


def _source_of(plant: Plant) -> tuple[str, Callable[[str], bytes]] | None:
    """The model's XML and a reader of the files it includes."""
    os.environ.setdefault("MUJOCO_GL", "disable")
    definition = getattr(plant, "definition", None)
    model_path = getattr(definition, "model_path", None)
    if model_path is not None:  # a task file's model, beside its file
        path = Path(model_path)
        root = ET.fromstring(path.read_text())
        _inline(root, lambda name: (path.parent / name).read_bytes(), depth=0)
        _absolute_asset_files(root, path.parent.resolve())
        return ET.tostring(root, encoding="unicode"), lambda name: (path.parent / name).read_bytes()
    bodies, actuators = getattr(plant, "bodies", None), getattr(plant, "actuators", None)
    if bodies is not None and actuators is not None:  # the lqr tasks: the model is drawn from the seed
        from dm_control.suite import lqr

        xml, assets = lqr.get_model_and_assets(bodies, actuators, np.random.RandomState(int(plant.seed)))
    elif isinstance(getattr(plant, "suite", None), tuple):  # a dm_control suite domain
        domain = importlib.import_module(f"dm_control.suite.{plant.suite[0]}")
        xml, assets = domain.get_model_and_assets()
    else:
        return None
    text = xml.decode() if isinstance(xml, bytes) else str(xml)
    return text, lambda name: _asset(assets, name)


def _asset(assets: dict[str, Any], name: str) -> bytes:
    for key in (name, os.path.normpath(name), "./" + os.path.normpath(name)):
        if key in assets:
            value = assets[key]
            return value if isinstance(value, bytes) else str(value).encode()
    raise FileNotFoundError(f"the model includes {name}, which its assets do not hold")


def inline_includes(text: str, read: Callable[[str], bytes]) -> str:
    """MJCF with every ``<include file=...>`` replaced by the children of the included file's root, as
    MuJoCo itself does; attribute values are kept as written."""
    root = ET.fromstring(text)
    _inline(root, read, depth=0)
    return ET.tostring(root, encoding="unicode")


ASSET_DIRS = {"mesh": "meshdir", "hfield": "meshdir", "skin": "meshdir", "texture": "texturedir"}


def _absolute_asset_files(root: ET.Element, folder: Path) -> None:
    """Every asset ``file`` (mesh, height field, skin, texture) as the absolute path MuJoCo would open, from the
    model's ``folder`` and its compiler's meshdir, texturedir or assetdir, which are then dropped."""
    dirs: dict[str, str] = {}
    compilers = root.findall(".//compiler")
    for compiler in compilers:
        for key in ("assetdir", "meshdir", "texturedir"):
            if key in compiler.attrib:
                dirs[key] = compiler.attrib[key]
    for tag, key in ASSET_DIRS.items():
        base = folder / dirs.get(key, dirs.get("assetdir", ""))
        for element in root.iter(tag):
            name = element.get("file")
            if name and not Path(name).is_absolute():
                element.set("file", str((base / name).resolve()))
    for compiler in compilers:
        for key in ("assetdir", "meshdir", "texturedir"):
            compiler.attrib.pop(key, None)


def _inline(element: ET.Element, read: Callable[[str], bytes], depth: int) -> None:
    if depth > 20:
        raise DescriptionError("includes nest more than 20 deep (an include cycle?)")
    children = list(element)
    for index, child in reversed(list(enumerate(children))):
        if child.tag == "include":
            included = ET.fromstring(read(str(child.get("file", ""))))
            _inline(included, read, depth + 1)
            element.remove(child)
            for offset, grandchild in enumerate(list(included)):
                element.insert(index + offset, grandchild)
        else:
            _inline(child, read, depth)


def mjcf_fingerprint(plant: Plant, mjcf: str) -> str:
    """The fingerprint ``plant.model_sha256()`` would give if its model were compiled from ``mjcf``.

    The plant's own code computes it, on a copy whose model is swapped for the compiled text, so the
    arrays hashed are exactly the ones the task fingerprints."""
    import mujoco

    try:
        compiled = mujoco.MjModel.from_xml_string(mjcf)
    except Exception as exc:  # MuJoCo's XML and compile errors are plain ValueErrors with the line
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DescriptionError(f"it does not compile as a MuJoCo model (MJCF): {first}") from None
    twin = copy.copy(plant)
    twin.physics = SimpleNamespace(model=compiled)  # type: ignore[attr-defined]
    return twin.model_sha256()


def described_fingerprint(run_dir: str | Path, mjcf: str) -> str | None:
    """The fingerprint of a robot's MJCF by the plant code of the run's task; None when the run folder cannot
    be read (the gate then refuses it with its own reason). A DescriptionError when the text does not compile."""
    path = Path(run_dir)
    run_file = path if path.is_file() else path / RUN_FILE
    try:
        with RunStore.open(run_file) as store:
            metadata = checked_metadata(store.metadata, run_file)
        task = task_of(metadata, run_file)
    except (RunFileError, UnknownTaskError):
        return None
    return mjcf_fingerprint(task.make_plant(metadata.seed), mjcf)
