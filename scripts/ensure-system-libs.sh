#!/usr/bin/env bash
# Installs the system libraries MuJoCo needs to render headless (EGL, OSMesa), and the Qt 5 GUI library
# EnvPool's ProcGen port loads (sessions with engine="envpool"), when they are missing.
set -euo pipefail
missing=()
ldconfig -p | grep -q 'libEGL.so.1' || missing+=(libegl1)
ldconfig -p | grep -q 'libEGL_mesa.so.0' || missing+=(libegl-mesa0)
ldconfig -p | grep -q 'libGL.so.1' || missing+=(libgl1)
ldconfig -p | grep -q 'libOSMesa.so' || missing+=(libosmesa6)
ldconfig -p | grep -q 'libQt5Gui.so.5' || missing+=(libqt5gui5)
ls /usr/lib/x86_64-linux-gnu/dri/swrast_dri.so >/dev/null 2>&1 || ls /usr/lib/*/dri/*swrast* >/dev/null 2>&1 || missing+=(libgl1-mesa-dri)
[ ${#missing[@]} -eq 0 ] && exit 0
echo "installing system libraries (headless rendering, Qt 5 GUI): ${missing[*]}"
sudo=""
[ "$(id -u)" -eq 0 ] || sudo="sudo"
$sudo apt-get update -qq
DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" libgles2 >/dev/null
