#!/usr/bin/env bash
# Install Debian's chromium when it is missing: the viewer's end-to-end test drives it
# headless (tests/test_viewer_e2e.py), and the viewer benchmark can attach it as a client.
# Never fatal: without chromium that test is skipped, everything else works.
set -uo pipefail
if command -v chromium >/dev/null 2>&1; then
  exit 0
fi
if ! command -v apt-get >/dev/null 2>&1; then
  echo "install_chromium: no apt-get here; install a chromium yourself to run the browser test"
  exit 0
fi
echo "install_chromium: installing chromium (headless browser for the viewer's end-to-end test)"
SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
($SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium) \
  >>"${TMPDIR:-/tmp}/tidee-setup-apt.log" 2>&1 || echo "install_chromium: could not install chromium; the viewer's browser test will be skipped"
exit 0
