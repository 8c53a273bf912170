#!/usr/bin/env bash
# Record the outputs of a fixed set of runs (rendered sets, camera and plane calibrations, a measured cloud,
# the demo) into folder $1, so that two versions of the code can be compared with compare_outputs.py.
set -euo pipefail
out=$(realpath -m "$1"); mkdir -p "$out"; cd "$out"
LP=${LP:-lightplane}
$LP render circle --out circles --n 8 --seed 3 --difficulty realistic
$LP calibrate-plane circles/*.png --camera circles/camera.json --diameter 50 -o plane.json
$LP render chessboard --stripe --out striped --n 6 --seed 4
$LP calibrate-plane-board striped/*.png --camera circles/camera.json --board 9x6 --square 8 -o plane_zhou.json
$LP demo --out demo --force
