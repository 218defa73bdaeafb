"""A run's seal: every message a run's nodes exchange carries an HMAC under the run's key, and every
receiver checks it, so nothing from outside the run (another sim or run on the domain, a stray
publisher, an impostor service) enters its dataset, its rollouts or its certificate.

Why an application-level HMAC: the Fast DDS in the ROS wheels of the Python registry is built
without the DDS Security plugins, so SROS2 cannot be switched on to authenticate publishers.

The key: npp-run draws a fresh random key for each run and hands it to its nodes in the
environment (``NPP_RUN_KEY``). Nodes started by hand share a key by exporting the same
``NPP_RUN_KEY`` in each terminal. Without one they use a fixed public key: a graph with a key of
its own is still kept apart, and data for another plant is still refused (below), but anyone on
the domain can then forge a tag.

The plant and the run: everything but the plant description is sealed under a key derived from the
run key, the plant's model fingerprint (:meth:`RunSeal.for_plant`) and the run's identity
(:meth:`RunSeal.for_run`), a random id the supervisor draws when it creates the run file and keeps
in it. So an expert's answer, a state or a rollout made for another plant, or recorded in another
run with the same key (an ``NPP_RUN_KEY`` exported once and reused for two runs), fails the check.
The identity travels in clear with what starts an exchange (a reset, an expert request, a dataset
trajectory); the receiver checks the message under that run's key and answers under it. The
supervisor alone knows which run is its own, and checks everything that may enter its data, returns
or certificate under its run's key: a replayed message of another run can at worst delay a node
that took it, never enter the run.

Where a tag goes: messages with a header carry ``context|tag`` in ``header.frame_id``, the context
being what the message does not say itself (the episode a state belongs to: sim stamps restart
every episode); npp_interfaces types without a header carry it in their ``seal`` field. The tag
covers every field of the message (the tag left out), walked in the message's own field order, so
a field that a message gains later is covered too. Not the serialized CDR bytes: they include
alignment padding that is not initialised, and differ between two processes for equal messages.
"""

from __future__ import annotations

import hmac
import os
import secrets
import struct
import sys
from array import array
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from sensor_msgs.msg import JointState

KEY_ENV = "NPP_RUN_KEY"
PUBLIC_KEY = b"npp_ros: no NPP_RUN_KEY given"
TAG_BYTES = 16
SEPARATOR = "|"


class SealError(ValueError):
    """A message that does not carry this run's seal: from outside the run, or altered."""


@dataclass(frozen=True)
class RunSeal:
    """Tags and checks messages under one key (the run's, or the run's for one plant)."""

    key: bytes
    private: bool  # whether the key is a secret; a public key keeps graphs apart but does not authenticate

    @classmethod
    def from_environment(cls, environ: Mapping[str, str] | None = None) -> RunSeal:
        value = (os.environ if environ is None else environ).get(KEY_ENV, "")
        return cls(value.encode(), True) if value else cls(PUBLIC_KEY, False)

    @staticmethod
    def new_key() -> str:
        """A fresh run key, as npp-run hands it to its nodes."""
        return secrets.token_hex(32)

    def for_plant(self, model_sha256: str) -> RunSeal:
        """The seal for everything about one plant: a tag made for another plant does not check."""
        return RunSeal(hmac.digest(self.key, b"plant:" + model_sha256.encode(), "sha256"), self.private)

    def for_run(self, run: str) -> RunSeal:
        """The seal for one run (of a plant seal): a tag made in another run does not check, even under the
        same key. ``run`` is the run's identity, as the supervisor's run file keeps it."""
        if not run:
            raise SealError("no run identity: only this run's supervisor names the run a message belongs to")
        return RunSeal(hmac.digest(self.key, b"run:" + run.encode(), "sha256"), self.private)

    def _tag(self, *messages: Any) -> str:
        parts: list[bytes] = []
        for message in messages:
            _canonical(message, parts)
        return hmac.digest(self.key, b"".join(parts), "sha256")[:TAG_BYTES].hex()

    def _fail(self, what: str, tag: str) -> SealError:
        return SealError(f"{what} does not carry this run's seal{_why(tag, self.private)}")

    # ------------------------------------------------------------ npp_interfaces types with a `seal` field
    def seal(self, msg: Any, answering: Any = None) -> Any:
        """Set msg.seal to the tag over the message and, for a service response, over the request it
        answers (so an answer cannot be passed off for another request); returns msg."""
        msg.seal = ""
        msg.seal = self._tag(answering, msg)
        return msg

    def check(self, msg: Any, what: str, answering: Any = None) -> None:
        """Raise SealError unless msg.seal is this run's tag of msg (and of the request it answers)."""
        tag = msg.seal
        msg.seal = ""
        try:
            ok = hmac.compare_digest(tag, self._tag(answering, msg))
        finally:
            msg.seal = tag
        if not ok:
            raise self._fail(what, tag)

    # ------------------------------------------------------------ messages with a header: frame_id = context|tag
    def seal_header(self, msg: Any, context: str = "") -> Any:
        """frame_id = "context|tag"; the context says what the message does not (a state's episode)."""
        msg.header.frame_id = context
        msg.header.frame_id = f"{context}{SEPARATOR}{self._tag(msg)}"
        return msg

    def check_header(self, msg: Any, what: str) -> str:
        """The context of a sealed message; SealError unless it carries this run's tag."""
        sealed = msg.header.frame_id
        context, _, tag = sealed.rpartition(SEPARATOR)
        msg.header.frame_id = context
        try:
            ok = hmac.compare_digest(tag, self._tag(msg))
        finally:
            msg.header.frame_id = sealed
        if not ok:
            raise self._fail(what, tag)
        return context


_FIELDS: dict[type, tuple[str, ...]] = {}  # a message class's field names, in declaration order


def _joint_state(msg: JointState, out: list[bytes]) -> None:
    """The control loop's message, every field, without the generic walk (a third of a control step's cost)."""
    stamp = msg.header.stamp
    frame, names = msg.header.frame_id.encode(), "\0".join(msg.name).encode()
    position, velocity, effort = msg.position, msg.velocity, msg.effort
    out += (
        struct.pack("<iIQQQQQ", stamp.sec, stamp.nanosec, len(frame), len(names), len(position), len(velocity),
                    len(effort)),
        frame, names, _doubles(position), _doubles(velocity), _doubles(effort),
    )  # fmt: skip


def _doubles(values: Any) -> bytes:
    if type(values) is array and values.typecode == "d" and sys.byteorder == "little":
        return values.tobytes()
    return struct.pack(f"<{len(values)}d", *values)


def _canonical(value: Any, out: list[bytes]) -> None:
    """Append an unambiguous byte encoding of a message, field by field in declaration order (None: nothing)."""
    kind = type(value)
    if kind is JointState:
        _joint_state(value, out)
        return
    names = _FIELDS.get(kind)
    if names is None and hasattr(kind, "get_fields_and_field_types"):
        names = _FIELDS[kind] = tuple(kind.get_fields_and_field_types())
    if names is not None:
        for name in names:
            _canonical(getattr(value, name), out)
    elif value is None:
        return
    elif kind is str:
        data = value.encode()
        out += (b"s", struct.pack("<Q", len(data)), data)
    elif kind is bool:
        out.append(b"?1" if value else b"?0")
    elif kind is int:
        out += (b"i", value.to_bytes(9, "little", signed=True))
    elif kind is float:
        out += (b"f", struct.pack("<d", value))
    elif kind is bytes:
        out += (b"b", struct.pack("<Q", len(value)), value)
    elif kind is array and sys.byteorder == "little":
        out += (b"a", value.typecode.encode(), struct.pack("<Q", len(value)), value.tobytes())
    elif kind is np.ndarray:
        data = np.ascontiguousarray(value, dtype=value.dtype.newbyteorder("<")).tobytes()
        out += (b"n", value.dtype.str.encode(), struct.pack("<Q", len(data)), data)
    elif kind in (list, tuple, array):
        out += (b"l", struct.pack("<Q", len(value)))
        for item in value:
            _canonical(item, out)
    else:
        raise TypeError(f"cannot seal a field of type {kind.__name__}")


def _why(tag: str, private: bool) -> str:
    if not tag:
        return " (it carries none: published from outside npp_ros, or by a node of an older version)"
    if private:
        return " (another key: another run, or a node started without this run's NPP_RUN_KEY)"
    return " (another key: another run's, or an NPP_RUN_KEY that this node was not given)"
