#!/bin/sh
# Debian's blender for the add-on's test in Blender itself (tests/test_blender_client.py::test_addon_in_blender
# runs it in background mode), with python3-numpy: Blender's glTF importer needs numpy and Debian's blender
# package does not depend on it.  FASTMESH_BLENDER overrides the command.
set -eu
BLENDER="${FASTMESH_BLENDER:-blender}"
if command -v "$BLENDER" >/dev/null 2>&1 && \
   "$BLENDER" --background --factory-startup --python-exit-code 1 --python-expr "import numpy" >/dev/null 2>&1; then
  exit 0
fi
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "[blender] $BLENDER with numpy not found: installing Debian's blender and python3-numpy" >&2
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq blender python3-numpy >/dev/null
else
  echo "[blender] $BLENDER (with numpy for its glTF importer) not found: install it (Debian: sudo apt-get" \
       "install blender python3-numpy) or set FASTMESH_BLENDER" >&2
  exit 1
fi
