"""Toolpath files: the canonical CSV (exact round trip) and an ABB RAPID module.

Canonical CSV
-------------
One header line, then one row per toolpath point, comma separated, no quoting:

``index,x_mm,y_mm,z_mm,ax,ay,az,speed_mm_s,kind,layer,spray_on,zone_mm``

* ``index``: 0-based row number (checked on reading);
* ``x_mm, y_mm, z_mm``: target point in the work object O [mm];
* ``ax, ay, az``: unit spray axis in O (from the nozzle towards the surface);
* ``speed_mm_s``: programmed speed of the move into the point [mm/s];
* ``kind``: ``infill``, ``edge``, ``skip`` or ``overhang`` (of the move into the point);
* ``layer``: 0-based layer index; ``spray_on``: 1 or 0; ``zone_mm``: blending radius [mm].

Floats are written with Python's ``repr`` (shortest text that reads back to the same float64),
so ``read_csv(write_csv(tp))`` reproduces every array exactly. ``meta`` is not stored; reading
rebuilds ``n_layers`` and ``layer_z_mm`` (the z of each layer's first point).

RAPID module
------------
``write_rapid`` writes a MODULE with one ``PROC main()`` of ``MoveL`` instructions to
robtargets in the work object (position [mm] with 3 decimals, orientation as the quaternion
(q1..q4 = qw, qx, qy, qz, 6 decimals) of the nozzle frame N whose +z is the spray axis and
whose +x is O's +x projected perpendicular to it); one ``speeddata`` per (kind, speed)
named ``v_<kind>_<n>``; one ``zonedata`` per zone radius (``fine`` for 0); ``nLayer := k;``
where a layer starts and ``SetDO doPowder`` where spraying switches. ``read_rapid`` parses such
a module back (positions and axes to the printed precision, speeds, kinds, zones, layers).
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from dm2.core.messages import KIND_CODE, TOOLPATH_KINDS, Toolpath

CSV_COLUMNS = ("index", "x_mm", "y_mm", "z_mm", "ax", "ay", "az", "speed_mm_s", "kind", "layer",
               "spray_on", "zone_mm")
RAPID_SPEED_DECIMALS = 3  # speeddata's v_tcp [mm/s] as written


def _atomic_write_text(path: str | Path, text: str) -> None:
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent or ".")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _meta_from_rows(position_O: np.ndarray, layer: np.ndarray) -> dict:
    if len(layer) == 0:
        return {"n_layers": 0, "layer_z_mm": []}
    n = int(layer.max()) + 1
    first = np.searchsorted(layer, np.arange(n))
    present = np.isin(np.arange(n), layer)
    z = [float(position_O[f, 2]) if ok else float("nan")
         for f, ok in zip(first, present, strict=True)]
    return {"n_layers": n, "layer_z_mm": z}


def format_csv(tp: Toolpath) -> str:
    """The canonical CSV text of ``tp``."""
    cols = [np.arange(len(tp)).tolist()]
    cols += [tp.position_O[:, k].tolist() for k in range(3)]
    cols += [tp.axis_O[:, k].tolist() for k in range(3)]
    cols.append(tp.speed_mm_s.tolist())
    cols.append(np.asarray(TOOLPATH_KINDS)[tp.kind].tolist())
    cols.append(tp.layer.tolist())
    cols.append(tp.spray_on.astype(np.int8).tolist())
    cols.append(tp.zone_mm.tolist())
    fmt = "{},{!r},{!r},{!r},{!r},{!r},{!r},{!r},{},{},{},{!r}"
    lines = [",".join(CSV_COLUMNS)]
    lines += [fmt.format(*row) for row in zip(*cols, strict=True)]
    return "\n".join(lines) + "\n"


def write_csv(tp: Toolpath, path: str | Path) -> None:
    """Write the canonical CSV (atomically: a temporary file renamed into place)."""
    _atomic_write_text(path, format_csv(tp))


def read_csv(path: str | Path) -> Toolpath:
    """Read a canonical CSV. Raises ValueError naming the file, line and column."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise FileNotFoundError(f"{path}: cannot read toolpath CSV: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a toolpath CSV (not UTF-8 text: byte {exc.start})") from None
    if not lines or tuple(lines[0].strip().split(",")) != CSV_COLUMNS:
        raise ValueError(f"{path}: line 1: header must be {','.join(CSV_COLUMNS)}")
    rows = [ln.split(",") for ln in lines[1:] if ln.strip()]
    n = len(rows)
    pos, axis = np.empty((n, 3)), np.empty((n, 3))
    speed, zone = np.empty(n), np.empty(n)
    kind = np.empty(n, np.int8)
    layer = np.empty(n, np.int32)
    spray = np.empty(n, bool)
    for i, r in enumerate(rows):
        where = f"{path}: line {i + 2}"
        if len(r) != len(CSV_COLUMNS):
            raise ValueError(f"{where}: expected {len(CSV_COLUMNS)} columns, got {len(r)}")
        v = {name: _csv_value(where, name, text) for name, text in zip(CSV_COLUMNS, r,
                                                                        strict=True)}
        if v["index"] != i:
            raise ValueError(f"{where}: column 'index' is {r[0]}, expected {i}")
        pos[i] = v["x_mm"], v["y_mm"], v["z_mm"]
        axis[i] = v["ax"], v["ay"], v["az"]
        if not np.any(axis[i]):
            raise ValueError(f"{where}: columns 'ax', 'ay', 'az' are all 0 (no spray axis)")
        speed[i], layer[i], spray[i], zone[i] = (v["speed_mm_s"], v["layer"], v["spray_on"],
                                                 v["zone_mm"])
        if r[8] not in KIND_CODE:
            raise ValueError(f"{where}: column 'kind' is {r[8]!r}, not one of {TOOLPATH_KINDS}")
        kind[i] = KIND_CODE[r[8]]
    return Toolpath(pos, axis, speed, kind, layer, spray, zone, meta=_meta_from_rows(pos, layer))


_CSV_INTS = ("index", "layer", "spray_on")
_CSV_POSITIVE = ("speed_mm_s",)
_CSV_NON_NEGATIVE = ("zone_mm",)


def _csv_value(where: str, column: str, text: str):
    """One cell of a canonical CSV row: an int, a finite float (positive or at least 0 where
    the column says so), or the kind's name; ValueError naming line, column and value."""
    if column == "kind":
        return text
    text = text.strip()
    try:
        value = int(text) if column in _CSV_INTS else float(text)
    except ValueError:
        raise ValueError(f"{where}: column '{column}' is {text!r}, not a "
                         f"{'whole number' if column in _CSV_INTS else 'number'}") from None
    if column in _CSV_INTS:
        if value < 0 or (column == "spray_on" and value > 1):
            raise ValueError(f"{where}: column '{column}' is {text!r}, expected "
                             + ("0 or 1" if column == "spray_on" else "0 or more"))
        return value
    if not np.isfinite(value) or abs(value) > 1e6:
        raise ValueError(f"{where}: column '{column}' is {text!r}, not a finite value "
                         "within 1 km")
    if (column in _CSV_POSITIVE and value <= 0) or (column in _CSV_NON_NEGATIVE and value < 0):
        raise ValueError(f"{where}: column '{column}' is {text!r}, expected a "
                         + ("positive value" if column in _CSV_POSITIVE else "value >= 0"))
    return value


def axis_to_quat_wxyz(axis_O: np.ndarray) -> np.ndarray:
    """Quaternions (qw, qx, qy, qz), qw >= 0, of nozzle frames whose +z is ``axis_O``, (n, 4)."""
    z = axis_O / np.linalg.norm(axis_O, axis=1)[:, None]
    ref = np.where(np.abs(z[:, :1]) > 0.99, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    x = ref - np.einsum("ij,ij->i", ref, z)[:, None] * z
    x /= np.linalg.norm(x, axis=1)[:, None]
    y = np.cross(z, x)
    q = Rotation.from_matrix(np.stack([x, y, z], axis=2)).as_quat()[:, [3, 0, 1, 2]]
    q[q[:, 0] < 0] *= -1
    return q


def _rapid_num(v: float, decimals: int) -> str:
    s = f"{v:.{decimals}f}"
    return "0" if float(s) == 0 else s.rstrip("0").rstrip(".")


def write_rapid(tp: Toolpath, path: str | Path, module_name: str = "DM2_Toolpath",
                tool: str = "tNozzle", wobj: str = "wobjPlate") -> None:
    """Write ``tp`` as an ABB RAPID module (atomically); see the module docstring."""
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]{0,31}", module_name):
        raise ValueError(f"write_rapid: module_name {module_name!r} is not a RAPID identifier")
    speeds: dict[tuple[int, float], str] = {}
    counts = dict.fromkeys(range(len(TOOLPATH_KINDS)), 0)
    for k, v in sorted(set(zip(tp.kind.tolist(), tp.speed_mm_s.tolist(), strict=True))):
        counts[k] += 1
        speeds[(k, v)] = f"v_{TOOLPATH_KINDS[k]}_{counts[k]}"
    zones = {z: ("fine" if z == 0 else f"z_path_{i}")
             for i, z in enumerate(sorted(set(tp.zone_mm.tolist())))}
    out = [f"MODULE {module_name}",
           f"  ! {len(tp)} points, {tp.n_layers} layers; written by dm2.toolpath.formats",
           "  PERS num nLayer := 0;"]
    for (_k, v), name in speeds.items():
        v_text = _rapid_num(v, RAPID_SPEED_DECIMALS)
        out.append(f"  CONST speeddata {name} := [{v_text},500,5000,1000];")
    for z, name in zones.items():
        if name != "fine":
            zs = _rapid_num(z, 3)
            out.append(f"  CONST zonedata {name} := [FALSE,{zs},{_rapid_num(1.5 * z, 3)},"
                       f"{_rapid_num(1.5 * z, 3)},{_rapid_num(0.15 * z, 3)},"
                       f"{_rapid_num(1.5 * z, 3)},{_rapid_num(0.15 * z, 3)}];")
    out.append("  PROC main()")
    quat = axis_to_quat_wxyz(tp.axis_O) if len(tp) else np.zeros((0, 4))
    layer_now, spray_now = None, None
    for i in range(len(tp)):
        if tp.layer[i] != layer_now:
            layer_now = int(tp.layer[i])
            out.append(f"    ! layer {layer_now}")
            out.append(f"    nLayer := {layer_now};")
        if bool(tp.spray_on[i]) != spray_now:
            spray_now = bool(tp.spray_on[i])
            out.append(f"    SetDO doPowder, {int(spray_now)};")
        p = ",".join(_rapid_num(v, 3) for v in tp.position_O[i])
        q = ",".join(_rapid_num(v, 6) for v in quat[i])
        out.append(f"    MoveL [[{p}],[{q}],[0,0,0,0],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]],"
                   f"{speeds[(int(tp.kind[i]), float(tp.speed_mm_s[i]))]},"
                   f"{zones[float(tp.zone_mm[i])]},{tool}\\WObj:={wobj};")
    out += ["  ENDPROC", "ENDMODULE"]
    _atomic_write_text(path, "\n".join(out) + "\n")


_SPEED_RE = re.compile(r"CONST\s+speeddata\s+(\w+)\s*:=\s*\[\s*([-+0-9.eE]+)")
_ZONE_RE = re.compile(r"CONST\s+zonedata\s+(\w+)\s*:=\s*\[\s*\w+\s*,\s*([-+0-9.eE]+)")
_MOVE_RE = re.compile(r"MoveL\s*\[\[([^\]]*)\],\[([^\]]*)\],[^;]*?\]\]\s*,\s*(\w+)\s*,\s*(\w+)")
_LAYER_RE = re.compile(r"nLayer\s*:=\s*(\d+)\s*;")
_DO_RE = re.compile(r"SetDO\s+doPowder\s*,\s*([01])\s*;")


def read_rapid(path: str | Path) -> Toolpath:
    """Parse a module written by :func:`write_rapid` back into a Toolpath."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise FileNotFoundError(f"{path}: cannot read RAPID module: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a RAPID module (not UTF-8 text: byte {exc.start})") from None
    speed_of = {m[1]: float(m[2]) for m in _SPEED_RE.finditer(text)}
    zone_of = {m[1]: float(m[2]) for m in _ZONE_RE.finditer(text)}
    zone_of["fine"] = 0.0
    pos, quat, speed, kind, layer, spray, zone = [], [], [], [], [], [], []
    layer_now, spray_now = 0, True
    for lineno, line in enumerate(text.splitlines(), start=1):
        if (m := _LAYER_RE.search(line)) and "PERS" not in line:
            layer_now = int(m[1])
        elif m := _DO_RE.search(line):
            spray_now = m[1] == "1"
        elif m := _MOVE_RE.search(line):
            where = f"{path}: line {lineno}"
            try:
                p = [float(v) for v in m[1].split(",")]
                q = [float(v) for v in m[2].split(",")]
            except ValueError:
                raise ValueError(f"{where}: robtarget is not numeric") from None
            if len(p) != 3 or len(q) != 4:
                raise ValueError(f"{where}: robtarget needs [x,y,z] and [q1,q2,q3,q4]")
            vname, zname = m[3], m[4]
            kname = vname.split("_")[1] if vname.count("_") >= 2 else ""
            if vname not in speed_of or kname not in KIND_CODE:
                raise ValueError(f"{where}: unknown speeddata {vname!r}")
            if zname not in zone_of:
                raise ValueError(f"{where}: unknown zonedata {zname!r}")
            pos.append(p)
            quat.append(q)
            speed.append(speed_of[vname])
            kind.append(KIND_CODE[kname])
            layer.append(layer_now)
            spray.append(spray_now)
            zone.append(zone_of[zname])
    q = np.asarray(quat, dtype=np.float64).reshape(-1, 4)
    axis = Rotation.from_quat(q[:, [1, 2, 3, 0]]).apply([0.0, 0.0, 1.0]) if len(q) else \
        np.zeros((0, 3))
    pos_arr = np.asarray(pos, dtype=np.float64).reshape(-1, 3)
    layer_arr = np.asarray(layer, dtype=np.int32)
    return Toolpath(pos_arr, axis, np.asarray(speed), np.asarray(kind, np.int8), layer_arr,
                    np.asarray(spray, bool), np.asarray(zone), meta=_meta_from_rows(pos_arr,
                                                                                      layer_arr))
