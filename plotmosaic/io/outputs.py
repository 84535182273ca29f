"""What a run will write, checked before any work: never an input, never a file the user made.

Every command states its inputs (files it reads, folders it reads from) and its outputs (single
files with every sibling it writes beside them, or an output folder with the top-level names it
writes there). `check_outputs` refuses, whatever --force says, an output that is or would replace an
input (compared by resolved path and by inode, so symlinks and hard links are caught); an existing
output file unless --force (every sibling is named in the plan, so a command that adds one cannot
forget to check it); and in an output folder:

- an existing entry of the run's own naming that no earlier run of the same command wrote (the
  user's own `report.md` in a register-plot folder): never replaced, even with --force;
- other entries the run did not write: refused unless --force, and left untouched with it.

`claimed` writes the folder's record (`.plotmosaic-run.json`: command -> names) before the work, so
a re-run or a resumed run of the same command may replace what an earlier one wrote; a run that
fails having written nothing leaves the record as it found it, byte for byte.
"""

from __future__ import annotations

import contextlib
import fnmatch
import json
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from plotmosaic.errors import InputError
from plotmosaic.io.atomic import TEMP_NAME, check_output_file, write_bytes_atomic, write_text_atomic

RECORD = ".plotmosaic-run.json"  # the output folder's record of the runs that wrote into it
_KIND = "plotmosaic output folder record"


@dataclass(frozen=True)
class Input:
    """A file (or, folder=True, every file under a folder) the run reads."""

    path: Path
    role: str  # how the message names it: "scan", "manifest", "poses file", ...
    folder: bool = False


@dataclass(frozen=True)
class OutputPlan:
    """Everything one run will write, and what it reads."""

    command: str
    inputs: tuple[Input, ...] = ()
    files: tuple[Path, ...] = ()  # single output files, every sibling included (align --out, ...)
    folder: Path | None = None  # the output folder, if the run writes one
    names: tuple[str, ...] = ()  # top-level entries it writes there (files, folders, `*` patterns)
    # replace existing output files; in a folder, write beside entries the run did not write
    # (never over them)
    force: bool = False
    replaces_folder: bool = False  # the whole folder is swapped for a new one (merge --tiles)
    kind: str = "output folder"  # how messages name the folder ("tile folder")
    legacy: str | None = None  # a sub-folder marking a folder this command wrote before records


@dataclass(frozen=True)
class RunRecord:
    """The commands that wrote into a folder and the names each writes."""

    runs: tuple[tuple[str, tuple[str, ...]], ...] = ()

    def names(self, command: str) -> tuple[str, ...]:
        return next((names for c, names in self.runs if c == command), ())

    def with_run(self, command: str, names: Iterable[str]) -> RunRecord:
        merged = tuple(sorted(set(self.names(command)) | set(names)))
        others = tuple((c, n) for c, n in self.runs if c != command)
        return RunRecord(tuple(sorted(others + ((command, merged),))))


def inputs_of(paths: Iterable[tuple[Path | str | None, str]]) -> tuple[Input, ...]:
    """Input records of (path, role) pairs; None (an option not given) is left out."""
    return tuple(Input(Path(p), role) for p, role in paths if p is not None)


def manifest_inputs(manifest) -> tuple[Input, ...]:
    """The manifest file, its scans and its ALS tiles."""
    found = [(manifest.source, "manifest")] if manifest.source is not None else []
    # a scan inside an E57 project is `plot.e57#3`: the file itself is the input
    found += [(manifest.resolve(s.file), f"scan {s.id!r}") for s in manifest.scans]
    found += [(manifest.resolve(t.path), "ALS tile") for t in manifest.als]
    return inputs_of(found)


# ---------------------------------------------------------------- inputs are never written


def _real(path: Path) -> Path:
    try:
        return Path(os.path.realpath(path))
    except (OSError, RuntimeError, ValueError):  # a symlink loop, an odd name: compare as given
        return Path(os.path.abspath(path))


def _same_inode(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):  # one of them does not exist (yet)
        return False


def replaces(out: Path, inp: Input) -> bool:
    """Writing `out` (a file, or a folder the run fills) would write over or into `inp`."""
    ro, ri = _real(out), _real(inp.path)
    if ro == ri or ri.is_relative_to(ro):
        return True
    if inp.folder and ro.is_relative_to(ri):
        return True
    return _same_inode(out, inp.path)


def _named(name: str, patterns: Iterable[str]) -> bool:
    return any(fnmatch.fnmatchcase(name, p) for p in patterns)


def _entries(folder: Path) -> list[str]:
    """The folder's entries, our temporaries and record left out; none if it does not exist."""
    try:
        names = sorted(os.listdir(folder))
    except (FileNotFoundError, NotADirectoryError):
        return []
    return [n for n in names if n != RECORD and not TEMP_NAME.match(n)]


def output_paths(plan: OutputPlan) -> list[Path]:
    """Every path the run will write: its files, and in its folder each name (patterns: the
    existing entries they match, and the inputs lying there that they match)."""
    paths = list(plan.files)
    if plan.folder is None:
        return paths
    folder = plan.folder
    if plan.replaces_folder:
        paths.append(folder)
    paths += [folder / n for n in plan.names if not _has_pattern(n)]
    patterns = [n for n in plan.names if _has_pattern(n)]
    paths += [folder / n for n in _entries(folder) if _named(n, patterns)]
    real = _real(folder)
    paths += [
        folder / i.path.name
        for i in plan.inputs
        if _real(i.path).parent == real and _named(i.path.name, patterns)
    ]
    return paths


def _has_pattern(name: str) -> bool:
    return any(c in name for c in "*?[")


def check_not_inputs(plan: OutputPlan) -> None:
    """Exit 2, naming the output, if it is or would replace an input, whatever --force says."""
    for out in output_paths(plan):
        for inp in plan.inputs:
            if replaces(out, inp):
                what = (
                    f"the {inp.role}"
                    if _real(out) == _real(inp.path)
                    else f"the {inp.role} {inp.path}"
                )
                raise InputError(
                    f"{out}: would replace {what}, an input of this run (inputs are never "
                    "written); choose another output"
                )


# ---------------------------------------------------------------- the output folder


def read_record(folder: Path) -> RunRecord:
    """The folder's record; an absent or unreadable one is an empty record."""
    try:
        data = json.loads((folder / RECORD).read_text(encoding="utf-8"))
        runs = data["runs"]
        return RunRecord(
            tuple(sorted((str(c), tuple(str(n) for n in names)) for c, names in runs.items()))
        )
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return RunRecord()


def _written_before(plan: OutputPlan, folder: Path) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Names earlier runs wrote here: (of this command, of any plotmosaic command), by the
    folder's record, or for a folder this command wrote before records existed, its own names."""
    record = read_record(folder)
    if not record.runs and plan.legacy is not None and (folder / plan.legacy).is_dir():
        return plan.names, plan.names
    return record.names(plan.command), tuple(n for _, names in record.runs for n in names)


def check_folder(plan: OutputPlan) -> None:
    """The output folder holds nothing the run would destroy (see the module's doc)."""
    folder = plan.folder
    if folder is None or not folder.is_dir():
        return
    ours, anyones = _written_before(plan, folder)
    foreign = []
    for name in _entries(folder):
        if _named(name, plan.names):
            if not plan.replaces_folder and not _named(name, ours):
                raise InputError(
                    f"{folder / name}: exists and was not written by plotmosaic {plan.command}; "
                    "not replacing it (move it away or choose another output folder)"
                )
        elif plan.replaces_folder or not _named(name, anyones):
            foreign.append(name)
    if not foreign:
        return
    more = f" (and {len(foreign) - 1} more)" if len(foreign) > 1 else ""
    if plan.replaces_folder:
        raise InputError(
            f"{folder}: holds {foreign[0]}{more}: not a {plan.kind} written by plotmosaic "
            f"{plan.command}, and the run replaces the whole folder; choose another output folder"
        )
    if not plan.force:
        raise InputError(
            f"{folder}: holds {foreign[0]}{more}, which no plotmosaic run wrote; "
            "use --force to write beside it (it is left untouched) or choose another output folder"
        )


def check_files(plan: OutputPlan) -> None:
    """Each output file writable, and not existing unless --force (exit 2, naming it)."""
    for path in plan.files:
        check_output_file(path, force=plan.force)


def check_outputs(plan: OutputPlan) -> OutputPlan:
    """All pre-work checks of a run's outputs; returns the plan."""
    check_not_inputs(plan)
    check_files(plan)
    check_folder(plan)
    return plan


def _record_bytes(folder: Path) -> bytes | None:
    try:
        return (folder / RECORD).read_bytes()
    except OSError:
        return None


def _write_record(folder: Path, record: RunRecord) -> None:
    """The record written, unless it already says exactly that (a re-run changes nothing)."""
    runs = {c: list(n) for c, n in record.runs}
    text = json.dumps({"kind": _KIND, "runs": runs}, indent=1)
    if _record_bytes(folder) != text.encode("utf-8"):
        write_text_atomic(folder / RECORD, text)


def _restore_record(folder: Path, before: bytes | None) -> None:
    """The record put back as it was (removed if there was none)."""
    if _record_bytes(folder) == before:
        return
    with contextlib.suppress(OSError):
        if before is None:
            (folder / RECORD).unlink()
        else:
            write_bytes_atomic(folder / RECORD, before)


@contextlib.contextmanager
def claimed(plan: OutputPlan) -> Iterator[OutputPlan]:
    """Record the run in its output folder before the work; a run that fails having written
    nothing there leaves neither the record nor a folder it created."""
    folder = plan.folder
    if folder is None or plan.replaces_folder:  # a replaced folder cannot keep a record
        yield plan
        return
    missing = []
    current = Path(os.path.abspath(folder))
    while not current.exists() and current.parent != current:
        missing.append(current)
        current = current.parent
    before = set(_entries(folder))
    parent = Path(os.path.abspath(folder)).parent
    records = {folder: _record_bytes(folder)}
    _write_record(folder, read_record(folder).with_run(plan.command, plan.names))
    if records.setdefault(parent, _record_bytes(parent)) is not None:
        # a folder inside another run's folder (report in DIR/report)
        _write_record(parent, read_record(parent).with_run(plan.command, [folder.name]))
    try:
        yield plan
    except BaseException:
        if set(_entries(folder)) <= before:  # the run wrote nothing: every record as it was
            for where, was in records.items():
                _restore_record(where, was)
            for d in missing:  # deepest first; only empty folders go
                with contextlib.suppress(OSError):
                    d.rmdir()
        raise
