"""``fastmesh loadtest --url URL --inputs DIR``: measure a FastMesh service with many simulated users."""

from __future__ import annotations

import json
import sys

from .flags import add_param_flags, given_params


def register(sub) -> None:
    p = sub.add_parser("loadtest", help="upload, poll and download with many clients; report throughput",
                       description="Simulated users upload the files of --inputs, poll their jobs (with back-off, "
                                   "honouring Retry-After) and download the results.  Stops by itself after "
                                   "--jobs uploads or --duration seconds (20 jobs if neither is given), then "
                                   "waits at most --grace seconds for accepted jobs; unfinished ones count as lost.")
    p.add_argument("--url", required=True, help="service address, e.g. http://127.0.0.1:8000")
    p.add_argument("--inputs", required=True, nargs="+", metavar="DIR",
                   help="directory (or files) of shapes to upload, used round-robin")
    p.add_argument("--concurrency", "-c", type=int, default=4, help="simulated users (default 4)")
    p.add_argument("--jobs", "-n", type=int, default=None, help="uploads in total (default 20 without --duration)")
    p.add_argument("--duration", type=float, default=None, help="stop uploading after this many seconds")
    p.add_argument("--grace", type=float, default=60.0,
                   help="seconds accepted jobs may still take after uploading stops (default 60)")
    p.add_argument("--api-key", default=None, help="bearer key (default: $FASTMESH_API_KEY)")
    p.add_argument("--format", default="glb", choices=("glb", "obj", "ply"), help="result format downloaded")
    p.add_argument("--formats", default=None, help="formats exported with each job (e.g. glb,obj)")
    add_param_flags(p, defaults=False)
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=_loadtest)


def _loadtest(args) -> int:
    import os

    import httpx

    from fastmesh.remote.client import form_values
    from fastmesh.remote.loadtest import LoadConfig, format_report, input_files, run

    params = form_values({**given_params(args), "formats": args.formats})
    input_files(args.inputs)  # a missing or empty input folder is a usage error, before any request
    key = args.api_key if args.api_key is not None else os.environ.get("FASTMESH_API_KEY")
    try:
        httpx.get(f"{args.url.rstrip('/')}/healthz", timeout=10).raise_for_status()
    except httpx.HTTPError as e:
        print(f"fastmesh loadtest: error: cannot reach {args.url}: {e}", file=sys.stderr)
        return 1
    cfg = LoadConfig(url=args.url, inputs=args.inputs, concurrency=args.concurrency, jobs=args.jobs,
                     duration=args.duration, grace=args.grace, api_key=key, params=params, fmt=args.format)
    report = run(cfg)
    print(json.dumps(report, indent=2) if args.json else format_report(report))
    # Non-zero when the service lost a job or nothing at all came back: scripts can gate on it.
    return 1 if report["jobs"]["lost"] or not report["jobs"]["succeeded"] else 0
