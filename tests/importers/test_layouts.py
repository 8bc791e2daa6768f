"""THuman4.0, AvatarReX and ActorsHQ layouts imported as capture format v1 (``avatar-prep import``), on sources built at
test time: a fake SMPL-X model (tests/importers/fake_smplx.py), a 6-frame fit, 4 cameras looking at the body,
flat-coloured silhouette images (posed vertices projected, triangles filled), grey JPEG masks (ActorsHQ: PNG),
one lost view (THuman4.0/AvatarReX; ActorsHQ lists none).

Checked: the capture validates (``load_capture``, ``check_images``), a lost view drops its frame, images are
links into the source (or copies), masks become 0/255 PNGs, the calibration conversion projects known points
as the source's own K/R/T (and distortion) do by hand (ActorsHQ: also from the csv's own numbers), the splits are
disjoint, paths that escape the source and unlisted missing files are refused, and ``avatar-prep all`` prepares the
imported capture (THuman4.0, ActorsHQ).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import csv

import cv2
import numpy as np
import pytest
import torch

from gsavatar.data_schema import check_images, load_capture
from gsavatar.geometry.camera import look_at, project
from gsavatar.geometry.lbs import RigTensors, lbs, skinning_transforms
from gsavatar.importers import SmplxParams, load_smplx_model, smplx_motion, smplx_template
from gsavatar.importers.layouts import LAYOUTS
from gsavatar.prep.cli import main as prep_main
from gsavatar.utils.io import read_mask
from importers.fake_smplx import random_fit, write_fake_smplx

F = 6  # frames of the fit
W, H = 96, 128  # image size
LOST = (1, 2)  # (camera index, frame) of the lost view
PREP_ARGS = ["--workers", "1", "--project.tex-size", "128", "--no-figures"]  # as tests/reliability/helpers.py
PROJ_TOL_PX = (
    1e-6  # float64 throughout; observed 0 (thuman4), 4e-14 px (avatarrex, with distortion), 3e-13 px (actorshq)
)
LAYOUT_NAMES = ["thuman4", "avatarrex", "actorshq"]


def has_lost_view(layout: str) -> bool:
    return layout != "actorshq"  # ActorsHQ has no list of lost views


def write_actorshq_calibration(file: Path, cams: list) -> None:
    """ActorsHQ's ``calibration.csv`` of world-to-camera (K, R, T) cameras, as HumanRF's ``write_calibration_csv``
    spells it: camera-to-world axis-angle (by OpenCV's Rodrigues, not ours), camera position, K over w/h."""
    with file.open("w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(["name", "w", "h", "rx", "ry", "rz", "tx", "ty", "tz", "fx", "fy", "px", "py"])
        for key, K, R, T, _ in cams:
            aa = cv2.Rodrigues(R.T)[0].ravel()  # world_from_cam rotation
            pos = -R.T @ T  # camera centre in the world
            norm = [K[0, 0] / W, K[1, 1] / H, K[0, 2] / W, K[1, 2] / H]  # fx, fy, px, py over the image size
            wr.writerow([key, W, H, *(repr(float(v)) for v in [*aa, *pos, *norm])])  # repr: full float64 precision


def source_cameras(layout: str) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(source key, K [3,3], R [3,3], T [3], dist [5]) of 4 cameras around the body, metres, OpenCV axes."""
    out = []
    keys = {
        "thuman4": ["cam00", "cam01", "cam02", "cam03"],
        "avatarrex": ["22010708", "22010710", "cam 3", "22070938"],
        "actorshq": ["Cam001", "Cam002", "Cam003", "Cam004"],
    }[layout]
    for i, key in enumerate(keys):
        a = 2 * np.pi * i / len(keys) + 0.3
        R, T = look_at(np.array([3.0 * np.sin(a), -0.2 + 0.3 * i, 3.0 * np.cos(a)]), np.array([0.0, -0.4, 0.0]))
        K = np.array([[150.0 + 5 * i, 0.0, W / 2 + i], [0.0, 151.0 + 5 * i, H / 2 - i], [0.0, 0.0, 1.0]])
        dist = np.array([0.01 * i, -0.005, 0.001, 0.0, 0.0]) if layout == "avatarrex" else np.zeros(5)
        out.append((key, K, R, T, dist))
    return out


def posed_vertices(model_path: Path, fit: dict) -> tuple[np.ndarray, np.ndarray]:
    """(posed vertices [F, V, 3], faces [T, 3]) by our LBS of the imported body (the silhouettes only need to
    show the body where the calibration says it is)."""
    model = load_smplx_model(model_path)
    params = SmplxParams.from_arrays(fit)
    body = smplx_template(model, params.betas)
    m = smplx_motion(params, model)
    args = [torch.from_numpy(a) for a in (m.pose, m.root_rotation, m.root_translation)]
    with torch.no_grad():
        T = skinning_transforms(RigTensors(body.rig), *args)
        v = lbs(
            torch.from_numpy(body.template.vertices),
            torch.from_numpy(body.template.skin_indices.astype(np.int64)),
            torch.from_numpy(body.template.skin_weights),
            T,
        )
    return v.numpy().astype(np.float64), body.template.faces


def make_source(root: Path, layout: str, model_path: Path) -> Path:
    """A THuman4.0-, AvatarReX- or ActorsHQ-layout capture in ``root`` (layout table: docs/import.md)."""
    fit = random_fit(F, seed=3)
    fit["transl"] = fit["transl"] * 0.2
    np.savez(root / "smpl_params.npz", **fit)
    verts, faces = posed_vertices(model_path, fit)
    cams = source_cameras(layout)
    calib = {}
    for i, (key, K, R, T, dist) in enumerate(cams):
        if layout == "thuman4":  # flat K/R lists and a column T, as some THuman4.0 files spell them
            calib[key] = {
                "K": K.ravel().tolist(),
                "R": R.ravel().tolist(),
                "T": T.reshape(3, 1).tolist(),
                "imgSize": [W, H],
            }
        elif layout == "avatarrex":
            calib[key] = {
                "K": K.tolist(),
                "R": R.tolist(),
                "T": T.tolist(),
                "distCoeff": [dist.tolist()],
                "imgSize": [W, H],
            }
        for f in range(F):
            px = project(verts[f], K, R, T, dist).pixels
            mask = np.zeros((H, W), np.uint8)
            cv2.fillPoly(mask, list(np.rint(px[faces] * 16).astype(np.int32)), 255, shift=4)
            img = np.full((H, W, 3), 40, np.uint8)
            img[mask > 0] = (60 + 40 * i, 150, 200 - 20 * f)
            if layout == "thuman4":
                img_file, mask_file = root / "images" / key / f"{f:08d}.jpg", root / "masks" / key / f"{f:08d}.jpg"
            elif layout == "avatarrex":
                img_file, mask_file = root / key / f"{f:08d}.jpg", root / key / "mask" / "pha" / f"{f:08d}.jpg"
            else:
                img_file = root / "4x" / "rgbs" / key / f"{key}_rgb{f:06d}.jpg"
                mask_file = root / "4x" / "masks" / key / f"{key}_mask{f:06d}.png"
            if (i, f) == LOST and has_lost_view(layout):
                continue
            for p, a in ((img_file, img), (mask_file, mask)):
                p.parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(p), a)
    if layout == "actorshq":
        write_actorshq_calibration(root / "4x" / "calibration.csv", cams)
        return root
    lost_key = cams[LOST[0]][0]
    if layout == "thuman4":  # the published lists hold Windows paths
        line = f"D:\\THuman4.0\\subject00\\images\\{lost_key}\\{LOST[1]:08d}.jpg"
    else:
        line = f"./avatarrex_zzr/{lost_key}/{LOST[1]:08d}.jpg"
    (root / "missing_img_files.txt").write_text(line + "\n")
    (root / ("calibration.json" if layout == "thuman4" else "calibration_full.json")).write_text(json.dumps(calib))
    return root


@pytest.fixture(scope="module")
def model_path(tmp_path_factory) -> Path:
    # a small tube body (1760 vertices): the importer does not need smplx's 9930 (its extra joints)
    return write_fake_smplx(tmp_path_factory.mktemp("smplx") / "SMPLX_NEUTRAL.npz", rings=4, segs=8)


@pytest.fixture(scope="module", params=LAYOUT_NAMES)
def source(request, tmp_path_factory, model_path) -> tuple[str, Path]:
    return request.param, make_source(tmp_path_factory.mktemp(request.param), request.param, model_path)


def run_import(layout: str, src: Path, model_path: Path, out: Path, *extra: str) -> int:
    return prep_main(
        ["import", "--layout", layout, "--src", str(src), "--smplx-model", str(model_path), "--out", str(out), *extra]
    )


def test_import_validates(source, model_path, tmp_path):
    layout, src = source
    out = tmp_path / "capture"
    assert run_import(layout, src, model_path, out) == 0
    cap = load_capture(out)
    check_images(cap)
    info = json.loads((out / "import.json").read_text())
    n = F - 1 if has_lost_view(layout) else F
    if has_lost_view(layout):
        assert info["source_frames"] == [f for f in range(F) if f != LOST[1]]  # the lost view's frame is dropped
        assert info["dropped_frames"] == {str(LOST[1]): [list(cap.cameras)[LOST[0]]]}
    else:
        assert info["source_frames"] == list(range(F)) and info["dropped_frames"] == {}
    assert cap.num_frames == n and cap.motion.num_frames == n
    assert set(cap.splits) == {"train", "test"}
    tr, te = cap.splits["train"], cap.splits["test"]
    assert te.cameras == [list(cap.cameras)[-1]] and te.frames == [n - 1]  # defaults: last camera, last 10% (>= 1)
    assert not set(tr.cameras) & set(te.cameras) and not set(tr.frames) & set(te.frames)
    if layout == "avatarrex":  # "cam 3" is not a plain name: mapped and recorded
        assert "cam02" in cap.cameras and info["cameras"]["cam02"] == "cam 3"
        assert np.allclose(cap.cameras["22010710"].dist, [0.01, -0.005, 0.001, 0, 0])
    img = cap.image_path(list(cap.cameras)[0], 0)
    assert img.is_symlink() and Path(os.readlink(img)).is_relative_to(src.resolve())
    m = cv2.imread(str(cap.mask_path(list(cap.cameras)[0], 0)), cv2.IMREAD_UNCHANGED)
    assert set(np.unique(m)) <= {0, 255} and 0.02 < read_mask(cap.mask_path(list(cap.cameras)[0], 0)).mean() < 0.5


def test_calibration_projects_as_the_source(source):
    """Known points through the source's K/R/T (+ distortion), by hand, and through our converted cameras. For
    ActorsHQ the file holds camera-to-world axis-angle, position and normalised intrinsics written from these
    K/R/T, so this checks the inversion and de-normalisation."""
    layout, src = source
    imported = LAYOUTS[layout].read(src)
    pts = np.array([[0.0, -0.4, 0.0], [0.3, 0.2, -0.1], [-0.2, -1.1, 0.25], [0.05, 0.5, 0.4]])
    for (key, K, R, T, dist), (name, cam) in zip(source_cameras(layout), imported.cameras.items()):
        assert imported.source_names[name] == key
        pc = pts @ R.T + T
        x, y = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
        k1, k2, p1, p2, k3 = dist
        r2 = x * x + y * y
        rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        xd, yd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        hand = np.stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]], 1)
        ours = project(pts, cam.K, cam.R, cam.T, cam.dist).pixels
        assert np.abs(hand - ours).max() < PROJ_TOL_PX, (layout, key)
        assert (cam.width, cam.height) == (W, H)


def test_options_copy_frames_and_split(tmp_path, model_path):
    (tmp_path / "src").mkdir()
    src = make_source(tmp_path / "src", "avatarrex", model_path)
    out = tmp_path / "cap"
    assert (
        run_import(
            "avatarrex",
            src,
            model_path,
            out,
            "--copy",
            "--frames",
            "0:5",
            "--cameras",
            "22010708",
            "cam02",
            "22070938",
            "--test-cameras",
            "22010708",
            "--test-frames",
            "3:5",
        )
        == 0
    )
    cap = load_capture(out)
    assert list(cap.cameras) == ["22010708", "cam02", "22070938"]  # the lost view's camera is not imported
    assert cap.num_frames == 5 and not cap.image_path("cam02", 0).is_symlink()
    assert cap.splits["test"].frames == [3, 4] and cap.splits["train"].frames == [0, 1, 2]
    # one camera cannot be both the train and the test camera: splits stay disjoint
    assert (
        run_import(
            "avatarrex", src, model_path, tmp_path / "cap2", "--cameras", "22010708", "--test-cameras", "22010708"
        )
        == 2
    )


def test_refuses_escapes_and_unlisted_missing_files(tmp_path, model_path, capsys):
    src = tmp_path / "src"
    src.mkdir()
    make_source(src, "thuman4", model_path)
    (src / "images" / "cam03" / "00000004.jpg").unlink()  # lost but not listed
    assert run_import("thuman4", src, model_path, tmp_path / "a") == 2
    assert "00000004.jpg" in capsys.readouterr().err
    cal = json.loads((src / "calibration.json").read_text())
    cal["../../outside"] = cal.pop("cam03")  # a camera key that would make the importer read outside the source
    (src / "calibration.json").write_text(json.dumps(cal))
    assert run_import("thuman4", src, model_path, tmp_path / "b") == 2
    assert "outside the source folder" in capsys.readouterr().err
    assert run_import("avatarrex", src, model_path, tmp_path / "c") == 2  # wrong layout: says which it looks like
    assert "--layout thuman4" in capsys.readouterr().err


@pytest.mark.parametrize("layout", ["thuman4", "actorshq"])
def test_prep_all_on_imported_capture(tmp_path, model_path, layout):
    src = tmp_path / "src"
    src.mkdir()
    make_source(src, layout, model_path)
    assert run_import(layout, src, model_path, tmp_path / "cap") == 0
    assert prep_main(["all", "--capture", str(tmp_path / "cap"), "--out", str(tmp_path / "ds"), *PREP_ARGS]) == 0


def test_actorshq_csv_conventions_and_resolution(tmp_path, model_path, capsys):
    """Known points projected by hand from the csv's own numbers (camera-to-world axis-angle by OpenCV, position,
    intrinsics times w/h) and through our converted cameras; ``--actorshq-resolution`` picks the folder; a csv
    with another header is refused naming the file."""
    src = make_source(tmp_path, "actorshq", model_path)
    imported = LAYOUTS["actorshq"].read(src)
    pts = np.array([[0.0, -0.4, 0.0], [0.3, 0.2, -0.1], [-0.2, -1.1, 0.25]])
    with (src / "4x" / "calibration.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [r["name"] for r in rows] == list(imported.cameras)
    for r in rows:
        v = {k: float(x) for k, x in r.items() if k != "name"}
        world_from_cam = cv2.Rodrigues(np.array([v["rx"], v["ry"], v["rz"]]))[0]
        pc = (pts - np.array([v["tx"], v["ty"], v["tz"]])) @ world_from_cam  # = R_c2w^T (x - position)
        hand = np.stack(
            [
                v["fx"] * v["w"] * pc[:, 0] / pc[:, 2] + v["px"] * v["w"],
                v["fy"] * v["h"] * pc[:, 1] / pc[:, 2] + v["py"] * v["h"],
            ],
            1,
        )
        cam = imported.cameras[r["name"]]
        assert np.abs(hand - project(pts, cam.K, cam.R, cam.T, cam.dist).pixels).max() < PROJ_TOL_PX, r["name"]
    # the same source in the 2x folder only: found with --actorshq-resolution 2x, refused without it
    (src / "4x").rename(src / "2x")
    assert run_import("actorshq", src, model_path, tmp_path / "a") == 2
    capsys.readouterr()
    assert run_import("actorshq", src, model_path, tmp_path / "b", "--actorshq-resolution", "2x") == 0
    assert json.loads((tmp_path / "b" / "import.json").read_text())["source_frames"] == list(range(F))
    (src / "2x" / "calibration.csv").write_text(
        "name,w,h,rx,ry,rz,tx,ty,tz,f,px,py\nCam001,96,128,0,0,0,0,0,3,1,0.5,0.5\n"
    )
    assert run_import("actorshq", src, model_path, tmp_path / "c", "--actorshq-resolution", "2x") == 2
    assert "calibration.csv: header" in capsys.readouterr().err
