#!/usr/bin/env bash
# The README's gallery, made by the public commands alone, on the CPU:
#
#     assets/gallery/make_gallery.sh [CLIP] [WORK]
#
# CLIP is a DAVIS clip folder with images/ and masks/ (default ../shared/data/davis/camel);
# WORK takes the scenes, shots and rendered frames (default out/gallery, ignored by git). The
# strips land in assets/gallery/. TOMGS names the command (default `tomgs`; from a checkout:
# TOMGS="python -m tomgs.cli" with PYTHONPATH=.); PYTHON runs the strip maker (numpy + cv2).
#
# The camel is selected by fitting it as its own layer (`fit --layer foreground`): the layer is the
# object and nothing else, and the background layer never saw it, so removing it leaves background.
# The background layer is temporal like any fit; half of its first Gaussians start alive over the
# whole clip, so the ground and the fence behind the camel, seen in other frames, fill the camel's
# place in this one. Every third frame of the whole clip, so that the camel has uncovered most of it.
set -euo pipefail
ARGS=("$@")
for i in "${!ARGS[@]}"; do ARGS[i]=$(realpath -m "${ARGS[i]}"); done  # paths given from here
cd "$(dirname "$0")/../.."                                                 # then the repository
CLIP=${ARGS[0]:-../shared/data/davis/camel}
WORK=${ARGS[1]:-out/gallery}
TOMGS=${TOMGS:-tomgs}
PYTHON=${PYTHON:-python3}
GALLERY=assets/gallery
CPU="--device cpu"
FIT="--frames 0:90:3 --max-side 240 $CPU"  # every third frame of the 90: 30 frames at 240x135
PICK=0:88:21                                # the strips' columns: frames 0, 21, 42, 63, 84
mkdir -p "$WORK" "$GALLERY"
: > "$WORK/times.txt"

run() {  # run a command, echo it and log its wall time
    echo "+ $*"
    local t0=$SECONDS
    "$@"
    echo "$(( SECONDS - t0 )) s  $*" >> "$WORK/times.txt"
}

# 1. Fit the clip as two layers (CPU, budgets in seconds of training).
run $TOMGS fit "$CLIP/images" --masks "$CLIP/masks" --layer foreground --budget 150 $FIT -o "$WORK/fg.ply"
run $TOMGS fit "$CLIP/images" --masks "$CLIP/masks" --layer background --budget 180 $FIT -o "$WORK/bg.ply"

# 2. The original row: the two layers together.
run $TOMGS render "$WORK/bg.ply" --layer "$WORK/fg.ply" --frames $PICK $CPU -o "$WORK/original"

# 3. Edits of the foreground (camel) layer, composited over the background.
#    Foreground axes: x right, y down, the plane z = 0 one unit in front of the camera; the
#    camel's feet are near y = 0.24, so scaling about (0, 0.24, 0) keeps it on the ground; the
#    copy goes left and 0.9 further away (z), so it stands smaller and higher, behind the original.
run $TOMGS edit "$WORK/fg.ply" -o "$WORK/fg_scaled.ply" --scale 1.3 --centre 0,0.24,0
run $TOMGS render "$WORK/bg.ply" --layer "$WORK/fg_scaled.ply" --frames $PICK $CPU -o "$WORK/scaled"
run $TOMGS edit "$WORK/fg.ply" -o "$WORK/fg_two.ply" --duplicate -0.6,0,0.9
run $TOMGS render "$WORK/bg.ply" --layer "$WORK/fg_two.ply" --frames $PICK $CPU -o "$WORK/duplicated"
#    Removal: the background layer alone.
run $TOMGS render "$WORK/bg.ply" --frames $PICK $CPU -o "$WORK/removed"

# 4. Physics on the camel layer, shrunk to 60% on its feet so that it has room to fall and bounce;
#    the floor is under its lowest point (the feet), gravity down the frame (+y). The shots are
#    rendered over the background layer (--over); --fps 25 steps the physics 1/25 s a frame, a
#    third of the fitted frames' real spacing (8.33 fps): slow motion, so the bounce spans frames.
run $TOMGS edit "$WORK/fg.ply" -o "$WORK/fg_small.ply" --scale 0.6 --centre 0,0.24,0
run $TOMGS simulate "$WORK/fg_small.ply" --drop 0.25 --stiffness 300 --fps 25 $CPU -o "$WORK/drop.npz" \
    --render "$WORK/drop" --over "$WORK/bg.ply"
run $TOMGS simulate "$WORK/fg_small.ply" --drop 0.25 --spin 0,0,6 --fps 25 $CPU -o "$WORK/spin.npz" \
    --render "$WORK/spin" --over "$WORK/bg.ply"
run $TOMGS render "$WORK/bg.ply" $CPU -o "$WORK/bg_all"     # every frame: where the shots differ from it

# 5. PNG strips: the original row above the edited one; the physics shots as one row each, with
#    the floor drawn under the lowest pixels where the shot differs from the background.
run $PYTHON - "$WORK" "$GALLERY" <<'PY'
import sys, pathlib
import cv2, numpy as np

work, gallery = map(pathlib.Path, sys.argv[1:])

def frames(folder, pick=None):
    files = sorted((work / folder).glob("*.png"))
    return [cv2.imread(str(files[i])) for i in (pick or range(len(files)))]

def row(images, labels):
    tiles = []
    for image, label in zip(images, labels + [""] * len(images)):  # labels: the first tiles'
        cv2.putText(image, label, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(np.pad(image, ((0, 2), (0, 2), (0, 0)), constant_values=255))  # white gutters
    return np.hstack(tiles)

def save(name, *rows):
    cv2.imwrite(str(gallery / name), np.vstack(rows)[:-2, :-2], [cv2.IMWRITE_PNG_COMPRESSION, 9])

def with_floor(folder, pick):
    shot = frames(folder)
    body = np.abs(np.stack(shot).astype(int) - np.stack(frames("bg_all"))).max(-1) > 60
    floor = np.flatnonzero(body.any(axis=(0, 2))).max()  # lowest row the body reaches
    picked = [shot[i].copy() for i in pick]
    for image in picked:
        image[floor + 1:floor + 3] = 110
    return row(picked, [f"frame {i}" for i in pick])

original = row(frames("original"), ["original"])
save("scale.png", original, row(frames("scaled"), ["scaled x1.3"]))
save("duplicate.png", original, row(frames("duplicated"), ["duplicated"]))
save("remove.png", original, row(frames("removed"), ["removed"]))
save("drop.png", with_floor("drop", [0, 7, 11, 16, 22]))
save("spin.png", with_floor("spin", [0, 5, 11, 15, 19, 26]))
PY
cat "$WORK/times.txt"
