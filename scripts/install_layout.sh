#!/usr/bin/env bash
# Complete the editable install in VENV to the layout colcon gives an ament_python package.
# `pip install -e .` (setuptools develop, honouring setup.cfg's script_dir) has put the
# executables in VENV/lib/csam_ros, where `ros2 run csam_ros <exe>` looks for them; this adds
# what develop skips: the ament index marker, share/csam_ros/package.xml, config/ and launch/,
# and puts the executables on the environment's PATH (VENV/bin). Usage: install_layout.sh VENV
set -euo pipefail
venv=$(cd "$1" && pwd)
root=$(cd "$(dirname "$0")/.." && pwd)
mkdir -p "$venv/share/ament_index/resource_index/packages" "$venv/share/csam_ros"
cp "$root/resource/csam_ros" "$venv/share/ament_index/resource_index/packages/csam_ros"
cp "$root/package.xml" "$venv/share/csam_ros/package.xml"
for exe in simulator smoother merger recorder player foxglove_bridge detections csam; do
  if [ ! -x "$venv/lib/csam_ros/$exe" ]; then
    echo "install_layout: $venv/lib/csam_ros/$exe is missing" >&2
    exit 1
  fi
  ln -sfn "../lib/csam_ros/$exe" "$venv/bin/$exe"
done
# parameter, params and scenario files, where csam_ros.core.model.config_file looks first, and
# the launch files, where `ros2 launch csam_ros FILE` looks (colcon installs a copy of each
# from setup.py's data_files; here a link keeps the source tree's files in use)
ln -sfn "$root/config" "$venv/share/csam_ros/config"
ln -sfn "$root/launch" "$venv/share/csam_ros/launch"
