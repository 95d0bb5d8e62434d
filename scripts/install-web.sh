#!/bin/sh
# three.js for the page (service/web): `npm ci` from the committed package-lock.json into
# service/web/node_modules (git-ignored).  Installs Debian's npm first when it is missing and we are root.
set -eu
cd "$(dirname "$0")/../service/web"
if ! command -v npm >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "[web] npm not found: installing Debian's npm" >&2
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq npm >/dev/null
  else
    echo "[web] npm is required for the page's three.js: install Node.js + npm (Debian: sudo apt-get install npm)" >&2
    exit 1
  fi
fi
npm ci --no-audit --no-fund --loglevel=error
