#!/bin/sh
# Debian's assimp-testmodels (model files in many formats written by other tools) for the real-file test
# (tests/test_assimp_corpus.py, scripts/assimp_corpus.py).  FASTMESH_ASSIMP_MODELS overrides the folder.
set -eu
MODELS="${FASTMESH_ASSIMP_MODELS:-/usr/share/assimp/models}"
[ -d "$MODELS" ] && exit 0
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "[assimp] $MODELS not found: installing Debian's assimp-testmodels" >&2
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq assimp-testmodels >/dev/null
else
  echo "[assimp] $MODELS not found: install it (Debian: sudo apt-get install assimp-testmodels) or set FASTMESH_ASSIMP_MODELS" >&2
  exit 1
fi
