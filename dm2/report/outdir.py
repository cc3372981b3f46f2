"""Output folders that never lose a user's file: a manifest of what dm2 wrote, checked before work.

Every folder a dm2 command writes (``--out``) holds ``.dm2-manifest.json``: the dm2 version, the
command, and the relative path of every file dm2 wrote there (a nested dm2 folder, such as
``report/`` of ``dm2 monitor``, has its own manifest and is listed as ``report/``).

Rules (:func:`check_output_dir`, before any work is done):

* a folder that does not exist, or is empty, is written;
* a folder holding a dm2 manifest and nothing else than the files listed in it is replaced
  (the earlier run's files are removed, the new ones written);
* a folder holding a manifest and other files too is refused unless ``force``: then only the
  manifest's files are replaced, every other file stays as it is;
* any other folder (files but no manifest) is refused, with or without ``force``;
* a file being read by the command (``inputs``) is never removed, even when a manifest lists it;
* every manifest entry must be a relative, normalised path inside the folder (no absolute path,
  no ``..``, no ``.``, not through a symlink that leads out of the folder): a manifest holding
  any other entry is refused (:class:`UnsafeManifest`) before a file is touched, and a symlink
  inside the folder is removed as a link, never followed.

A refusal is an :class:`OutputRefused` (a ``ValueError``: the CLI exits 2) naming the folder and
up to three of the files that would have been at risk.
"""

from __future__ import annotations

import json
import logging
import os
import posixpath
import shutil
from pathlib import Path

log = logging.getLogger(__name__)

MANIFEST_NAME = ".dm2-manifest.json"
MANIFEST_SCHEMA = 1


class OutputRefused(ValueError):
    """The output folder cannot be written without putting files dm2 did not write at risk."""


class OutputNotWritable(OutputRefused):
    """The system does not let dm2 write there (permission, a read-only file system)."""


class UnsafeManifest(OutputRefused):
    """A manifest lists an entry outside its folder (absolute, ``..``, through a symlink)."""


def _entry_problem(folder: Path, entry) -> str | None:
    """Why ``entry`` of the manifest of ``folder`` may not be used, or None when it is a
    relative, normalised path inside the folder (a nested folder ends with ``/``)."""
    if not isinstance(entry, str) or not entry.strip("/"):
        return "is not a file name"
    name = entry[:-1] if entry.endswith("/") else entry
    if "\0" in name or "\\" in name:
        return "holds a NUL or backslash"
    if posixpath.isabs(name) or os.path.isabs(name):
        return "is an absolute path"
    parts = name.split("/")
    if any(p in ("", ".", "..") for p in parts):
        return "is not a normalised path inside the folder ('..', '.' or an empty part)"
    root = os.path.realpath(folder)
    parent = os.path.realpath(os.path.join(folder, *parts[:-1]))
    real = os.path.realpath(os.path.join(folder, *parts)) if entry.endswith("/") else parent
    if os.path.commonpath([root, parent]) != root or os.path.commonpath([root, real]) != root:
        return "leads out of the folder through a symlink"
    return None


def read_manifest(folder: str | Path) -> dict | None:
    """The folder's manifest (``{"schema", "dm2", "command", "files"}``) or None when it has
    none or it is not one dm2 wrote. Raises :class:`UnsafeManifest` naming the manifest and
    the entry when an entry is not a relative, normalised path inside the folder."""
    path = Path(folder) / MANIFEST_NAME
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not isinstance(data, dict) or not isinstance(data.get("files"), list) \
            or data.get("schema") != MANIFEST_SCHEMA:
        return None
    for entry in data["files"]:
        problem = _entry_problem(Path(folder), entry)
        if problem is not None:
            raise UnsafeManifest(f"{path}: entry {entry!r} {problem}; dm2 touched nothing "
                                 "(a manifest lists only files inside its own folder): remove "
                                 "that entry, or choose a new folder")
    return data


def write_manifest(folder: str | Path, files, command: str = "") -> Path:
    """Write (replace) the manifest of ``folder`` listing ``files`` (relative paths; a nested
    dm2 folder as ``"name/"``)."""
    from dm2 import __version__

    folder = Path(folder)
    entries = sorted({str(f).replace(os.sep, "/") for f in files if str(f) != MANIFEST_NAME})
    path = folder / MANIFEST_NAME
    tmp = folder / f"{MANIFEST_NAME}.part"  # replaced whole: a full disk keeps the old one
    try:
        tmp.write_text(json.dumps({"schema": MANIFEST_SCHEMA, "dm2": __version__,
                                   "command": command, "files": entries}, indent=1),
                       encoding="utf-8")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def add_to_manifest(folder: str | Path, files, command: str | None = None) -> None:
    """Add ``files`` to the manifest of ``folder`` (created when absent)."""
    old = read_manifest(folder) or {"files": [], "command": ""}
    write_manifest(folder, [*old["files"], *files],
                   command=old.get("command", "") if command is None else command)


def files_below(folder: Path) -> list[str]:
    """Every file and link below ``folder`` as relative POSIX paths (directories excluded)."""
    out = []
    for root, dirs, names in os.walk(folder, followlinks=False):
        rel = Path(root).relative_to(folder)
        for d in list(dirs):
            if (Path(root) / d).is_symlink():
                names.append(d)
                dirs.remove(d)
        out.extend((rel / n).as_posix() for n in names)
    return sorted(out)


def owned_files(folder: Path) -> set[str] | None:
    """Files below ``folder`` that dm2's manifests list (nested manifests included), or None
    when ``folder`` holds no manifest."""
    manifest = read_manifest(folder)
    if manifest is None:
        return None
    owned = {MANIFEST_NAME}
    for entry in manifest["files"]:
        if entry.endswith("/"):
            sub = owned_files(folder / entry.rstrip("/"))
            if sub is not None:
                owned.update(f"{entry}{f}" for f in sub)
        else:
            owned.add(entry)
    return owned


def foreign_files(folder: Path) -> list[str]:
    """Files below ``folder`` no dm2 manifest lists (all of them without a manifest)."""
    owned = owned_files(folder) or set()
    return [f for f in files_below(folder) if f not in owned]


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_output_dir(out_dir: str | Path, *, force: bool = False, inputs=()) -> Path:
    """Refuse (OutputRefused naming the folder) an output folder dm2 may not write; returns
    the absolute folder. See the module docstring for the rules."""
    out = Path(out_dir).absolute()
    parent = out.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if out.exists() and not out.is_dir():
        raise OutputRefused(f"output folder {out}: exists and is not a folder")
    target = out if out.exists() else parent
    if not os.access(target, os.W_OK | os.X_OK):
        raise OutputNotWritable(f"output folder {out}: {target} is not writable")
    for inp in inputs:
        if inp is not None and _same_file(Path(inp), out):
            raise OutputRefused(f"output folder {out}: is the input {inp}")
    if not out.exists() or not any(out.iterdir()):
        return out
    if read_manifest(out) is None:
        shown = ", ".join(files_below(out)[:3]) or "only folders"
        raise OutputRefused(f"output folder {out}: holds files dm2 did not write ({shown}); "
                            "choose a new folder (dm2 replaces only folders it wrote itself)")
    foreign = foreign_files(out)
    if foreign and not force:
        shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more"
                                          if len(foreign) > 3 else "")
        raise OutputRefused(f"output folder {out}: holds an earlier dm2 run and files dm2 did "
                            f"not write ({shown}); choose a new folder, or give --force to "
                            "replace only dm2's files and keep the others")
    return out


def clear_outputs(out_dir: str | Path, inputs=()) -> list[str]:
    """Remove the files the manifest of ``out_dir`` lists (nested dm2 folders likewise), never
    one of ``inputs`` nor any unlisted file; folders left empty are removed. Returns the
    relative paths kept because they are inputs."""
    out = Path(out_dir)
    manifest = read_manifest(out)
    if manifest is None:
        return []
    inputs = [Path(p) for p in inputs if p is not None]
    kept: list[str] = []
    for entry in manifest["files"]:
        if entry.endswith("/"):
            sub = out / entry.rstrip("/")
            kept.extend(f"{entry}{k}" for k in clear_outputs(sub, inputs))
            _remove_empty_dirs(sub)
            continue
        path = out / entry
        if not (path.is_file() or path.is_symlink()):
            continue
        if any(_same_file(path, inp) for inp in inputs):
            kept.append(entry)
            continue
        path.unlink()
        _remove_empty_dirs(path.parent, stop=out)
    (out / MANIFEST_NAME).unlink(missing_ok=True)
    return kept


def _remove_empty_dirs(folder: Path, stop: Path | None = None) -> None:
    """Remove ``folder`` and its empty parents up to (not including) ``stop`` while empty."""
    folder = Path(folder)
    while folder.is_dir() and not folder.is_symlink() and folder != stop \
            and not any(folder.iterdir()):
        folder.rmdir()
        folder = folder.parent
        if stop is None:
            break


def install_folder(tmp: Path, out: Path, inputs=()) -> None:
    """Put the finished folder ``tmp`` (holding its manifest) in place of ``out``: renamed
    when ``out`` is absent or empty, else the earlier run's files are cleared
    (:func:`clear_outputs`) and each new file moved in; files dm2 did not write stay."""
    if out.is_dir() and not any(out.iterdir()):
        out.rmdir()
    if not out.exists():
        tmp.rename(out)
        return
    owned = owned_files(out) or set()
    new_files = files_below(tmp)
    clash = [rel for rel in new_files if rel != MANIFEST_NAME and rel not in owned
             and ((out / rel).exists() or (out / rel).is_symlink())]
    if clash:  # a file a user put there has the name of one dm2 writes: keep both
        keep = out.with_name(f"{out.name}.dm2-{os.getpid()}")
        tmp.rename(keep)
        raise OutputRefused(f"output folder {out}: {', '.join(clash[:3])} there was not written "
                            f"by dm2 and is left as it is; this run's output is in {keep}")
    kept = set(clear_outputs(out, inputs)) & set(new_files)
    if kept:  # never write over the input being read
        keep = out.with_name(f"{out.name}.dm2-{os.getpid()}")
        tmp.rename(keep)
        raise OutputRefused(f"output folder {out}: {', '.join(sorted(kept)[:3])} is this "
                            f"run's input and is left as it is; this run's output is in {keep}")
    new = read_manifest(tmp) or {"files": [], "command": ""}
    for rel in new_files:
        dest = out / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        if dest.is_dir() and not dest.is_symlink():
            raise OutputRefused(f"output folder {out}: {rel} is a folder dm2 did not write")
        os.replace(tmp / rel, dest)
    shutil.rmtree(tmp, ignore_errors=True)
    log.debug("%s: replaced %d files of an earlier run", out, len(new["files"]))


def prepare_output_dir(out_dir: str | Path, *, force: bool = False, inputs=()) -> set[str]:
    """Check ``out_dir`` (:func:`check_output_dir`), create it and clear an earlier dm2 run's
    files; returns the files left there (a user's, kept), for :func:`claim_outputs`."""
    out = check_output_dir(out_dir, force=force, inputs=inputs)
    out.mkdir(parents=True, exist_ok=True)
    clear_outputs(out, inputs)
    return set(files_below(out))


def claim_outputs(out_dir: str | Path, before: set[str], command: str) -> None:
    """Write the manifest of ``out_dir``: every file there now that was not in ``before``."""
    out = Path(out_dir)
    write_manifest(out, [f for f in files_below(out) if f not in before], command=command)


def discard_partial(folder: str | Path, before: set[str]) -> None:
    """After a failed write into ``folder`` (a full disk, say): the files this run left there
    (not in ``before``) are listed in the manifest, so a rerun replaces them without
    ``--force``; a half-written ``.part`` file is removed, as is every other new file when the
    manifest itself cannot be written. A file that was there before is never touched."""
    folder = Path(folder)
    if not folder.is_dir():
        return
    new = [f for f in files_below(folder) if f not in before and f != MANIFEST_NAME]
    for rel in [f for f in new if f.endswith(".part")]:
        (folder / rel).unlink(missing_ok=True)
    rest = [f for f in new if not f.endswith(".part")]
    try:
        listed = read_manifest(folder)
        write_manifest(folder, [*(listed or {"files": []})["files"], *rest],
                       command=(listed or {}).get("command", ""))
    except (OSError, ValueError):
        for rel in rest:
            (folder / rel).unlink(missing_ok=True)


def written_by_dm2(path: Path) -> bool:
    """Whether the single file ``path`` is one dm2 writes: an MCAP recording whose header
    names the library ``dm2``, a canonical toolpath CSV, a RAPID module dm2 generated, or a
    PNG carrying dm2's ``Software`` tag."""
    try:
        with open(path, "rb") as f:
            head = f.read(512)
    except OSError:
        return False
    if head.startswith(b"\x89MCAP0\r\n") and len(head) > 21:
        at = 8 + 1 + 8  # magic, header opcode, record length
        n = int.from_bytes(head[at:at + 4], "little")
        at += 4 + n  # profile string
        m = int.from_bytes(head[at:at + 4], "little")
        return head[at + 4:at + 4 + m] == b"dm2"
    if head.startswith(b"\x89PNG"):
        return b"Software\x00dm2" in head
    text = head.decode("utf-8", errors="replace")
    return text.startswith("index,x_mm,y_mm,z_mm,") or (
        text.startswith("MODULE ") and "written by dm2" in text)


def check_output_file(path: str | Path, *, force: bool = False, inputs=()) -> Path:
    """Refuse (OutputRefused) a single output file that is an input, a folder, or an existing
    file dm2 did not write (unless ``force``: the user asks for it to be replaced)."""
    path = Path(path).absolute()
    for inp in inputs:
        if inp is not None and _same_file(Path(inp), path):
            raise OutputRefused(f"output file {path}: is the input {inp}")
    if path.is_dir():
        raise OutputRefused(f"output file {path}: is a folder")
    if not path.parent.is_dir():
        raise OutputRefused(f"output file {path}: folder {path.parent} does not exist")
    part = path.with_name(path.name + ".part")  # where a recording is written first
    for p in (path, part):
        if p.exists() and not force and not written_by_dm2(p):
            raise OutputRefused(f"output file {path}: {p} exists and was not written by dm2; "
                                "choose another name, or give --force to replace it")
    if not os.access(path.parent, os.W_OK | os.X_OK):
        raise OutputNotWritable(f"output file {path}: folder {path.parent} is not writable")
    return path
