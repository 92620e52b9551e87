"""The slot-frame kernel's loop-invariant arguments as one compiled object (``FrameCall``).

numba's dispatcher unboxes every array argument of a call, about 55 ns each: the fused
velocity Verlet step (the pair template's ``frame_verlet``) takes the slot frame's
arrays, the parameter table and its scratch, sixteen arrays that stay the same from one
list build to the next, and passing them one by one cost 1.8 us a call against 1.1 us as
one numba StructRef (measured at 108 atoms: a struct is unboxed as one pointer). A
``FrameCall`` is made by :func:`frame_call` (about 3 us) and takes a new list's slots by
:func:`set_slots` (about 1 us); under
``NUMBA_DISABLE_JIT=1`` it is a plain namespace with the same fields, which the template's
Python twin reads alike.
"""

from __future__ import annotations

from types import SimpleNamespace

from numba import config, njit
from numba.core import types
from numba.experimental import structref

#: The fields, in the order :func:`frame_call` takes them: the frame_forces arguments
#: but the positions, cutoff mode, virial and single-type flags and forces.
FIELDS = (
    "types",
    "slots",
    "n_types",
    "table",
    "data",
    "frame",
    "frame_types",
    "buffers",
    "energies",
    "virials",
)


@structref.register
class FrameCallType(types.StructRef):
    """numba's type of a :class:`FrameCall` (its fields' types, literals made plain)."""

    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(kind)) for name, kind in fields)


class FrameCall(structref.StructRefProxy):
    """The loop-invariant arguments of one slot-frame kernel call (see :data:`FIELDS`)."""


structref.define_proxy(FrameCall, FrameCallType, list(FIELDS))


def set_slots(call, slots) -> None:
    """Put a new list's slot arrays (``slots``, of the same types) into ``call``: after a
    build, one compiled call (about 1 us) rather than a new FrameCall (about 4)."""
    if config.DISABLE_JIT:
        call.slots = slots
    else:
        _set_slots(call, slots)


def frame_call(*values):
    """A :class:`FrameCall` of ``values`` (in :data:`FIELDS`' order); a namespace of them
    under ``NUMBA_DISABLE_JIT``."""
    if len(values) != len(FIELDS):
        raise TypeError(f"frame_call takes {len(FIELDS)} values, got {len(values)}")
    if config.DISABLE_JIT:
        return SimpleNamespace(**dict(zip(FIELDS, values, strict=True)))
    return _frame_call(*values)


@njit(cache=True)
def _frame_call(types, slots, n_types, table, data, frame, frame_types, buffers, energies, virials):
    return FrameCall(
        types, slots, n_types, table, data, frame, frame_types, buffers, energies, virials
    )


@njit(cache=True)
def _set_slots(call, slots):
    call.slots = slots
