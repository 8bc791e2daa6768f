"""Single-file outputs (export PLY, turntable mp4, figures): a user's file is never replaced silently."""

from __future__ import annotations


import numpy as np
import pytest

from gsavatar.utils.errors import SchemaError
from gsavatar.utils.outdir import PLY_COMMENT, claim_output_file, file_record_path, is_our_file, record_output_file
from tests.reliability.test_hostile_outputs import assert_refused, run_cli


def test_existing_foreign_file_is_refused_and_force_allows_it(tmp_path):
    notes = tmp_path / "notes.ply"
    notes.write_text("my notes\n")
    with pytest.raises(SchemaError, match="notes.ply.*not a gsavatar ply output.*--force"):
        claim_output_file(notes, "ply")
    assert claim_output_file(notes, "ply", force=True) == notes
    assert notes.read_text() == "my notes\n"  # claiming writes nothing


@pytest.mark.parametrize(
    "kind,name", [("ply", "thesis.txt"), ("video", "clip.avi"), ("figure", "fig.jpg"), ("video", "noext")]
)
def test_extension_must_fit_the_kind(tmp_path, kind, name):
    with pytest.raises(SchemaError, match="must end in"):
        claim_output_file(tmp_path / name, kind)


def test_directories_links_and_fifos_are_refused(tmp_path):
    (tmp_path / "d.png").mkdir()
    with pytest.raises(IsADirectoryError):
        claim_output_file(tmp_path / "d.png", "figure")
    target = tmp_path / "real.png"
    target.write_bytes(b"x")
    (tmp_path / "link.png").symlink_to(target)
    with pytest.raises(SchemaError, match="not a regular file"):
        claim_output_file(tmp_path / "link.png", "figure", force=True)
    import os

    os.mkfifo(tmp_path / "pipe.mp4")
    with pytest.raises(SchemaError, match="not a regular file"):
        claim_output_file(tmp_path / "pipe.mp4", "video", force=True)


def test_our_outputs_are_recognised_by_content_not_name(tmp_path):
    from gsavatar.models.ply import read_ply, write_ply

    ply = tmp_path / "a.ply"
    n = 3
    write_ply(
        ply,
        np.zeros((n, 3)),
        np.tile([1.0, 0, 0, 0], (n, 1)),
        np.full((n, 3), 0.01),
        np.full(n, 0.5),
        np.zeros((n, 1, 3)),
    )
    assert PLY_COMMENT.encode() in ply.read_bytes()[:512]
    assert is_our_file(ply, "ply") and read_ply(ply).means.shape == (n, 3)  # readers skip the comment
    claim_output_file(ply, "ply")  # a re-run replaces its own file
    png = tmp_path / "f.png"
    png.write_bytes(b"\x89PNG fake")
    record_output_file(png, "figure")
    assert is_our_file(png, "figure") and file_record_path(png).exists()
    png.write_bytes(b"\x89PNG the user's own, saved over ours")  # same name, other content: not ours any more
    assert not is_our_file(png, "figure")
    with pytest.raises(SchemaError, match="not a gsavatar figure"):
        claim_output_file(png, "figure")


def test_companion_json_of_a_new_figure_is_not_overwritten(tmp_path):
    (tmp_path / "fig.json").write_text('{"mine": 1}')
    with pytest.raises(SchemaError, match="fig.json"):
        claim_output_file(tmp_path / "fig.png", "figure", companions=(tmp_path / "fig.json",))


def test_export_onto_a_users_file_exits_2_and_keeps_it(pose_only_run, tmp_path, capsys):
    from gsavatar.train.cli import main

    for name in ("notes.ply", "thesis.txt"):
        f = tmp_path / name
        f.write_text("the user's words\n")
        rc = run_cli(main, ["export", "--run", str(pose_only_run), "--out", str(f)])
        assert_refused(capsys, rc, name)
        assert f.read_text() == "the user's words\n"
    out = tmp_path / "avatar.ply"
    assert run_cli(main, ["export", "--run", str(pose_only_run), "--out", str(out)]) == 0
    assert run_cli(main, ["export", "--run", str(pose_only_run), "--out", str(out)]) == 0  # its own file: replaced
    f = tmp_path / "notes.ply"
    assert run_cli(main, ["export", "--run", str(pose_only_run), "--out", str(f), "--force"]) == 0
    assert is_our_file(f, "ply")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["avatar.ply", "notes.ply", "thesis.txt"]  # no temp left


def test_turntable_onto_a_users_video_exits_2(pose_only_run, tmp_path, capsys):
    from gsavatar.train.cli import main

    f = tmp_path / "holiday.mp4"
    f.write_bytes(b"not ours")
    rc = run_cli(main, ["turntable", "--run", str(pose_only_run), "--out", str(f), "--views", "2", "--size", "32"])
    assert_refused(capsys, rc, "holiday.mp4")
    assert f.read_bytes() == b"not ours"
