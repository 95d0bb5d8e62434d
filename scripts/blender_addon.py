"""Build the Blender add-on's zip: ``clients/blender/*.py`` as the package ``fastmesh_blender/``, which is what
Blender's Preferences > Add-ons > Install takes.  Entries carry a fixed date, so the same sources give the
same zip.

    python3 scripts/blender_addon.py [build/fastmesh_blender.zip]
"""

from __future__ import annotations

import sys
import zipfile
from pathlib import Path

ADDON = "fastmesh_blender"  # the module name Blender registers the add-on under
SOURCE = Path(__file__).resolve().parent.parent / "clients" / "blender"
OUT = Path(__file__).resolve().parent.parent / "build" / f"{ADDON}.zip"


def build(out: Path = OUT) -> Path:
    """Write the zip to ``out`` (its folder made as needed); returns ``out``."""
    out.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        for path in sorted(SOURCE.glob("*.py")):
            info = zipfile.ZipInfo(f"{ADDON}/{path.name}", date_time=(2020, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            info.compress_type = zipfile.ZIP_DEFLATED
            z.writestr(info, path.read_bytes())
    return out


if __name__ == "__main__":
    print(build(Path(sys.argv[1]) if len(sys.argv) > 1 else OUT))
