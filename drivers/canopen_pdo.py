"""The CANopen driver's PDO codec: PDO layouts from an EDS, scaling to and from counts.

The mappings and scalings are described in :mod:`drivers.canopen`'s docstring (the EDS
files in ``config/`` are the source of truth); everything here is also importable from
:mod:`drivers.canopen`, and the soft PLC's nodes use the same functions.
"""

from __future__ import annotations

import io
import math
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import canopen
import numpy as np
from canopen import objectdictionary as od_types

from gateway.core.files import MAX_EDS_BYTES, read_regular
from gateway.core.resources import data_dir
from gateway.errors import DriverInitError, DriverIOError

TENSION_N_PER_COUNT = 0.02
VELOCITY_M_S_PER_COUNT = 2e-5
LENGTH_M_PER_COUNT = 1e-4
POSITION_M_PER_COUNT = 1e-4
ANGLE_RAD_PER_COUNT = 1e-4
TENSION_NO_VALUE = 0x7FFF
TENSION_MIN_N = -32767 * TENSION_N_PER_COUNT  # what encode_tension writes without clamping
TENSION_MAX_N = 32766 * TENSION_N_PER_COUNT
STATUS_BITS = 2

_STRUCT_CODES = {
    od_types.INTEGER8: "b",
    od_types.UNSIGNED8: "B",
    od_types.INTEGER16: "h",
    od_types.UNSIGNED16: "H",
    od_types.INTEGER32: "i",
    od_types.UNSIGNED32: "I",
}


@dataclass(frozen=True)
class PdoLayout:
    """One PDO as mapped in an EDS: COB-ID, mapped objects in order, and its codec."""

    number: int  # 1-based PDO number
    cob_id: int
    trans_type: int
    entries: tuple[tuple[int, int], ...]  # (index, subindex) in frame order
    codec: struct.Struct  # little-endian, byte-aligned

    @property
    def slots(self) -> tuple[tuple[int, int], ...]:
        """(object index, position in that object's value list): sub 0 -> 0, sub k -> k-1."""
        return tuple((i, max(s - 1, 0)) for i, s in self.entries)

    def retarget(self, cob_id: int) -> PdoLayout:
        return PdoLayout(self.number, cob_id, self.trans_type, self.entries, self.codec)


def resolve_path(path: str | Path) -> Path:
    """``path`` as given when it exists, else one of the shipped EDS files (config/)."""
    p = Path(path)
    return p if p.is_absolute() or p.exists() else data_dir() / p


def import_eds(eds_path: str | Path, node_id: int) -> Any:
    """The object dictionary of an EDS file, read through the one bounded file reader
    (a regular file under a size limit: a device, a FIFO or a huge file is refused)."""
    path = resolve_path(eds_path)
    raw = read_regular(path, MAX_EDS_BYTES, "EDS file")
    fp = io.StringIO(raw.decode("utf-8", errors="replace"))
    fp.name = str(path)  # canopen picks the format by the name's suffix
    return canopen.import_od(fp, node_id)


def load_pdo_layouts(
    eds_path: str | Path, node_id: int
) -> tuple[dict[int, PdoLayout], dict[int, PdoLayout]]:
    """(TPDOs, RPDOs) of an EDS by PDO number; only enabled PDOs with a mapping."""
    path = resolve_path(eds_path)
    try:
        od = import_eds(path, node_id)
        network = canopen.Network()  # never connected: only to satisfy PdoMap.subscribe
        node = canopen.LocalNode(node_id, od)
        network.add_node(node)
        node.tpdo.read(from_od=True)
        node.rpdo.read(from_od=True)
    except Exception as exc:
        raise DriverInitError(f"{path}: cannot load EDS: {exc}") from exc
    return _layouts(path, node.tpdo.map), _layouts(path, node.rpdo.map)


def _layouts(path: Path, maps: Any) -> dict[int, PdoLayout]:
    """PdoLayouts of the enabled, non-empty maps of one canopen ``PdoMaps`` (or None)."""
    layouts: dict[int, PdoLayout] = {}
    for number, pdo_map in (maps or {}).items():
        if not pdo_map.enabled or not pdo_map.cob_id or not len(pdo_map.map):
            continue
        fmt = "<"
        for var in pdo_map.map:
            code = _STRUCT_CODES.get(var.od.data_type)
            if code is None or var.offset % 8 or var.length != 8 * struct.calcsize(code):
                raise DriverInitError(
                    f"{path}: PDO {number} maps {var.index:04X}h.{var.subindex}: "
                    "only byte-aligned integer objects are supported"
                )
            fmt += code
        entries = tuple((v.index, v.subindex) for v in pdo_map.map)
        layouts[number] = PdoLayout(
            number, pdo_map.cob_id, pdo_map.trans_type, entries, struct.Struct(fmt)
        )
    return layouts


# --- scaling ----------------------------------------------------------------------------
def to_int16(value: float, per_count: float) -> int:
    """Round ``value / per_count`` to int16, clamped to -32768..32767 (NaN -> 0)."""
    if value != value:
        return 0
    return max(-32768, min(32767, round(value / per_count)))


def encode_tension(value_n: float) -> int:
    """Corrected tension -> int16 count (0.02 N); NaN/inf -> 0x7FFF, else clamped."""
    if not math.isfinite(value_n):
        return TENSION_NO_VALUE
    return max(-32767, min(32766, round(value_n / TENSION_N_PER_COUNT)))


def decode_tension(count: int) -> float:
    return math.nan if count == TENSION_NO_VALUE else count * TENSION_N_PER_COUNT


def pack_status(status: Any) -> int:
    """(m,) channel status values (0..2) -> status word, 2 bits per channel."""
    word = 0
    for i, s in enumerate(status):
        word |= (int(s) & 0x3) << (STATUS_BITS * i)
    return word


def unpack_status(word: int, out: np.ndarray) -> None:
    for i in range(out.shape[0]):
        out[i] = (word >> (STATUS_BITS * i)) & 0x3


def new_slots(layouts: dict[int, PdoLayout]) -> dict[int, list[int]]:
    """A zeroed value list for every object the layouts map, long enough for its subs."""
    sizes: dict[int, int] = {}
    for layout in layouts.values():
        for index, pos in layout.slots:
            sizes[index] = max(sizes.get(index, 0), pos + 1)
    return {index: [0] * n for index, n in sizes.items()}


def pack_pdo(layout: PdoLayout, slots: dict[int, list[int]]) -> bytes:
    return layout.codec.pack(*[slots[i][p] for i, p in layout.slots])


def unpack_pdo(layout: PdoLayout, data: bytes | bytearray, slots: dict[int, list[int]]) -> None:
    """Decode one frame into ``slots``; a frame shorter than the mapping is an IO error."""
    if len(data) < layout.codec.size:
        raise DriverIOError(
            f"PDO 0x{layout.cob_id:03X}: {len(data)} data bytes, mapping needs {layout.codec.size}"
        )
    for (index, pos), value in zip(layout.slots, layout.codec.unpack_from(data), strict=True):
        slots[index][pos] = value
