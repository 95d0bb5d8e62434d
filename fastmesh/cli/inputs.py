"""What ``fastmesh generate`` makes of INPUT and OUTPUT: one file, or a folder of shapes.

A folder is a person's folder: it holds notes beside the shapes (``readme.txt``), and after one run it holds
the results too (``chair.off.glb`` beside ``chair.off`` when OUTPUT is INPUT).  Neither is an input: a text
file whose first line is not a point, and a file named after another input plus an export format, are
skipped with a line on stderr, so the same command can be run again into the same folder.
"""

from __future__ import annotations

from pathlib import Path

from fastmesh.shapes.shape import EXPORT_FORMATS, SUPPORTED_FORMATS

TEXT_POINT_FORMATS = ("xyz", "txt")
SNIFF_BYTES = 4096  # enough for a comment header and the first row of numbers


def _ext(path: Path) -> str:
    return path.suffix.lower().lstrip(".")


def output_format(output: Path, fmt: str | None) -> str:
    """The format of a single OUTPUT file: its extension, else ``--format``, else glb.

    ``generate`` and ``submit`` both ask it, so the two refuse the same names.

    Parameters
    ----------
    output : Path
        The file to write.
    fmt : str or None
        ``--format`` (``submit`` has none: None).

    Raises
    ------
    ValueError
        OUTPUT is a folder, its extension is not a format we write (``x.stl``, ``x.fbx``: GLB bytes under that
        name open nowhere), or ``--format`` names another export format than OUTPUT's extension.
    """
    if output.is_dir():
        raise ValueError(f"cannot write {output}: it is a folder; name the output file (e.g. {output / 'result.glb'})")
    ext = _ext(output)
    if ext and ext not in EXPORT_FORMATS:
        written = ", ".join(f".{f}" for f in EXPORT_FORMATS[:-1]) + f" or .{EXPORT_FORMATS[-1]}"
        raise ValueError(f"cannot write {output}: the output must end in {written} (the formats written), not "
                         f"{output.suffix}; name it {output.with_suffix('.' + (fmt or EXPORT_FORMATS[0])).name}")
    if fmt and ext and ext != fmt:
        raise ValueError(f"--format {fmt} does not match the output file {output} (a .{ext} file); name it "
                         f"{output.with_suffix('.' + fmt).name} or leave --format out")
    return ext or fmt or "glb"


def first_row_is_a_point(path: Path) -> bool:
    """Whether a text point file's first line that is neither blank nor a ``#`` comment holds 3 or 6 numbers
    (commas count as spaces, as the loader reads them)."""
    with open(path, "rb") as fh:
        head = fh.read(SNIFF_BYTES)
    for raw in head.replace(b"\r", b"\n").split(b"\n"):
        line = raw.strip()
        if not line or line.startswith(b"#"):
            continue
        parts = line.replace(b",", b" ").split()
        try:
            [float(p) for p in parts]
        except ValueError:
            return False
        return len(parts) in (3, 6)
    return False


def why_skipped(path: Path, names: set[str]) -> str | None:
    """Why a file found in the folder is not an input (None when it is one).

    Parameters
    ----------
    path : Path
        A file in the folder with a supported extension.
    names : set of str
        The names of every such file in ``path``'s folder.
    """
    stem = Path(path.name)
    while _ext(stem) in EXPORT_FORMATS:  # chair.off.glb, and chair.off.glb.glb made from it by a run before
        stem = Path(stem.stem)
        if stem.name in names:
            return f"a result of {stem.name} (this tool's output)"
    if _ext(path) in TEXT_POINT_FORMATS and not first_row_is_a_point(path):
        return "not a point file (its first line is not 3 or 6 numbers)"
    return None


def folder_jobs(src: Path, out: Path, fmt: str | None, glob: str | None
                ) -> tuple[list[tuple[Path, Path, str]], list[tuple[Path, str]]]:
    """``(jobs, skipped)`` for a folder INPUT: ``(input, output, format)`` per shape, ``(file, reason)`` per
    file left out.  ``IN/a/chair.off`` becomes ``OUT/a/chair.off.<fmt>``: the source extension stays in the
    name, so ``chair.off`` and ``chair.ply`` give two results.

    Parameters
    ----------
    src, out : Path
        The INPUT and OUTPUT folders.
    fmt : str or None
        ``--format``; glb when None.
    glob : str or None
        ``--glob`` pattern, relative to ``src`` (``*.ply``, ``**/*.obj``); every file below ``src`` when None.

    Raises
    ------
    ValueError
        No shape found, or a result would overwrite an input.
    """
    fmt = fmt or "glb"
    own = out.resolve()
    found = sorted(f for f in src.glob(glob or "**/*") if f.is_file() and _ext(f) in SUPPORTED_FORMATS)
    if src.resolve() in own.parents:  # results of an earlier run into a folder inside INPUT are not inputs either
        found = [f for f in found if own not in f.resolve().parents]
    names: dict[Path, set[str]] = {}
    for f in found:
        names.setdefault(f.parent, set()).add(f.name)
    jobs, skipped = [], []
    for f in found:
        reason = why_skipped(f, names[f.parent])
        if reason:
            skipped.append((f, reason))
        else:
            jobs.append((f, out / f.relative_to(src).with_name(f"{f.name}.{fmt}"), fmt))
    if not jobs:
        what = f"matching {glob!r}" if glob else f"(extensions: {', '.join(SUPPORTED_FORMATS)})"
        raise ValueError(f"no readable shapes in {src} {what}")
    inputs = {f.resolve() for f, _, _ in jobs}
    clash = next((dst for _, dst, _ in jobs if dst.resolve() in inputs), None)
    if clash is not None:
        raise ValueError(f"output {clash} would overwrite an input; choose another output folder")
    return jobs, skipped


def generate_jobs(input: str, output: str, fmt: str | None, glob: str | None
                  ) -> tuple[list[tuple[Path, Path, str]], list[tuple[Path, str]]]:
    """``(jobs, skipped)`` of ``fastmesh generate``: :func:`folder_jobs` for a folder, else the one file.

    Raises
    ------
    FileNotFoundError
        INPUT does not exist.
    ValueError
        ``--glob`` with a file INPUT, a format that does not match OUTPUT, or what :func:`folder_jobs` raises.
    """
    src, out = Path(input), Path(output)
    if src.is_dir():
        return folder_jobs(src, out, fmt, glob)
    if not src.exists():
        raise FileNotFoundError(f"no such file: {src}")
    if glob:
        raise ValueError(f"--glob chooses files in a folder; {src} is a file")
    return [(src, out, output_format(out, fmt))], []
