"""Upload every file of Debian's assimp-testmodels that FastMesh accepts by extension; report what became of each.

    python scripts/assimp_corpus.py --url http://127.0.0.1:8000 [--root /usr/share/assimp/models] [--json]

Hundreds of model files written by other people's exporters (and some deliberately odd ones).  Each
file of an accepted extension (obj glb gltf ply stl off xyz txt npy npz) is uploaded; it must end as

* ``result``: accepted and the job succeeded (the mesh downloaded),
* ``failed``: accepted, and the job failed with a clear code (e.g. ``no_faces`` from a random model),
* ``rejected``: a 4xx JSON error, with its code and message (the reason),
* ``crashed``: anything else: a 5xx, no answer, a job failed with ``internal``/``worker_lost``, or a job
  still unfinished after ``--timeout`` seconds.  There must be none: the exit code is 1 otherwise.

Install the files with ``sh scripts/install-assimp-testmodels.sh`` (Debian: ``apt-get install assimp-testmodels``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

ROOT = Path("/usr/share/assimp/models")
CRASH_CODES = ("internal", "worker_lost")


def corpus_files(root: Path) -> list[Path]:
    from fastmesh.shapes.shape import SUPPORTED_FORMATS

    return sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower().lstrip(".") in SUPPORTED_FORMATS)


def run_corpus(url: str, files: list[Path], root: Path, api_key: str | None = None, params: dict | None = None,
               timeout: float = 120.0) -> dict:
    """Upload ``files`` one by one, then wait for every accepted job.  Returns counts and one row per file."""
    from fastmesh.remote.client import Client, JobFailed, ServiceError

    rows: list[dict] = []
    pending: list[tuple[dict, str]] = []
    with Client(url, api_key=api_key, retries_429=20) as c:
        for path in files:
            row = {"file": str(path.relative_to(root)), "bytes": path.stat().st_size}
            rows.append(row)
            try:
                job = c.submit(path, **(params or {}))
            except ServiceError as e:
                if 400 <= e.status < 500:
                    row.update(outcome="rejected", code=e.code, reason=e.message[:200], http=e.status)
                else:
                    row.update(outcome="crashed", code=e.code, reason=e.message[:200], http=e.status)
                continue
            row["input"] = job["input"]
            pending.append((row, job["id"]))
        deadline = time.monotonic() + timeout
        for row, job_id in pending:
            try:
                job = c.wait(job_id, timeout=max(1.0, deadline - time.monotonic()), interval=0.1, max_interval=1.0)
                c.download(job_id, fmt="glb")
                row.update(outcome="result", vertices=job["result"]["vertices"], faces=job["result"]["faces"])
            except JobFailed as e:
                bad = e.code in CRASH_CODES
                row.update(outcome="crashed" if bad else "failed", code=e.code, reason=e.message[:200])
            except TimeoutError as e:
                row.update(outcome="crashed", code="stuck", reason=str(e))
            except ServiceError as e:
                row.update(outcome="crashed", code=e.code, reason=e.message[:200], http=e.status)
    counts = Counter(r["outcome"] for r in rows)
    return {
        "files": len(rows),
        "accepted": sum(1 for r in rows if "input" in r),
        "result": counts["result"], "failed": counts["failed"], "rejected": counts["rejected"],
        "crashed": counts["crashed"],
        "by_extension": {ext: dict(Counter(r["outcome"] for r in rows if r["file"].lower().endswith("." + ext)))
                         for ext in sorted({r["file"].rsplit(".", 1)[1].lower() for r in rows})},
        "rejected_reasons": dict(Counter(f"{r['code']}: {_reason(r['reason'])}" for r in rows
                                         if r["outcome"] == "rejected").most_common()),
        "failed_codes": dict(Counter(r["code"] for r in rows if r["outcome"] == "failed")),
        "rows": rows,
    }


def _reason(message: str) -> str:
    """The message without file-specific numbers and names, so that equal reasons group."""
    import re

    m = re.sub(r"'[^']*'", "'…'", message)
    m = re.sub(r"\d+", "N", m)
    return m[:90]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--url", required=True, help="FastMesh service, e.g. http://127.0.0.1:8000")
    ap.add_argument("--root", type=Path, default=ROOT, help=f"corpus folder (default {ROOT})")
    ap.add_argument("--api-key", default=None)
    ap.add_argument("--max-vertices", type=int, default=None, help="per job (small = fast with a test model)")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds for all accepted jobs to finish")
    ap.add_argument("--json", action="store_true", help="print the full report (one row per file) as JSON")
    args = ap.parse_args(argv)
    if not args.root.is_dir():
        print(f"assimp_corpus: {args.root} not found; install it: sh scripts/install-assimp-testmodels.sh",
              file=sys.stderr)
        return 2
    files = corpus_files(args.root)
    params = {"max_vertices": args.max_vertices} if args.max_vertices else {}
    rep = run_corpus(args.url, files, args.root, args.api_key, params, args.timeout)
    if args.json:
        print(json.dumps(rep, indent=2))
    else:
        for r in rep["rows"]:
            detail = (f"{r['vertices']} v, {r['faces']} f" if r["outcome"] == "result"
                      else f"{r.get('code')}: {r.get('reason', '')[:100]}")
            print(f"{r['outcome']:<9} {r['file']:<70} {detail}")
        print(f"\n{rep['files']} files: {rep['accepted']} accepted ({rep['result']} result, {rep['failed']} failed "
              f"clearly), {rep['rejected']} rejected, {rep['crashed']} crashed")
        for reason, n in rep["rejected_reasons"].items():
            print(f"  rejected {n:>3} x {reason}")
    return 1 if rep["crashed"] else 0


if __name__ == "__main__":
    sys.exit(main())
