"""``fastmesh submit FILE --url URL [-o OUT]``: send a shape to a FastMesh service, wait, download."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path


def register(sub) -> None:
    from .flags import add_param_flags

    p = sub.add_parser("submit", help="send a shape to a FastMesh service and download the mesh")
    p.add_argument("file", help="mesh or point cloud (obj, glb, gltf, ply, stl, off, xyz, txt, npy, npz)")
    p.add_argument("--url", required=True, help="service address, e.g. http://127.0.0.1:8000")
    p.add_argument("-o", "--out", default=None, help="where to write the result (default: FILE's name + .glb); "
                                                     "the extension picks glb, obj or ply; none: glb")
    p.add_argument("--api-key", default=None, help="bearer key (default: $FASTMESH_API_KEY)")
    add_param_flags(p, defaults=False)
    p.add_argument("--timeout", type=float, default=None, help="give up after this many seconds")
    p.add_argument("--json", action="store_true", help="print the finished job as JSON on stdout")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=_submit)


def _submit(args) -> int:
    from fastmesh.remote.client import Client, ServiceError

    from .flags import given_params
    from .inputs import output_format

    src = Path(args.file)
    if not src.is_file():
        raise FileNotFoundError(f"no such file: {src}")
    out = Path(args.out) if args.out else src.with_suffix(".glb")
    fmt = output_format(out, None)  # the names `generate` refuses, refused alike
    t0 = time.monotonic()

    def show(job: dict) -> None:
        if args.quiet:
            return
        pr = job["progress"]
        bar = "#" * int(20 * (pr["fraction"] or 0))
        print(f"\r{job['status']:<9} {pr['stage'] or '':<10} [{bar:<20}] {100 * (pr['fraction'] or 0):5.1f}%  "
              f"{time.monotonic() - t0:6.1f}s", end="", file=sys.stderr, flush=True)

    try:
        with Client(args.url, api_key=args.api_key) as client:
            job = client.submit(src, formats=fmt, **given_params(args))
            job = client.wait(job["id"], progress=show, timeout=args.timeout)
            client.download(job["id"], out)
    except (ServiceError, TimeoutError) as e:
        if not args.quiet:
            print(file=sys.stderr)
        print(f"fastmesh submit: error: {e}", file=sys.stderr)
        return 1
    if not args.quiet:
        print(file=sys.stderr)
        from .generate import faces_text

        r = job["result"]
        faces = faces_text(r["faces"], r.get("quality") or {})
        print(f"wrote {out} ({r['vertices']} vertices, {faces}) in {time.monotonic() - t0:.1f} s",
              file=sys.stderr)
    if args.json:
        print(json.dumps(job, indent=2))
    return 0
