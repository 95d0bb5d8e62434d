#!/bin/sh
# Debian's chromium for the browser tests (tests/test_web_browser.py drives it with playwright; the
# playwright-managed browser download is never used).  FASTMESH_CHROMIUM overrides the path.
set -eu
CHROMIUM="${FASTMESH_CHROMIUM:-/usr/bin/chromium}"
[ -x "$CHROMIUM" ] && exit 0
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "[chromium] $CHROMIUM not found: installing Debian's chromium" >&2
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
else
  echo "[chromium] $CHROMIUM not found: install it (Debian: sudo apt-get install chromium) or set FASTMESH_CHROMIUM" >&2
  exit 1
fi
