"""Two processes claiming one output folder at once (torchrun ranks of one prep stage).

A CI run once failed ``test_torchrun_two_gloo_ranks_equal_one``: rank 1 was between creating the marker's temp
file and renaming it when rank 0 looked, so rank 0 saw a non-empty folder with no marker and refused it.
"""

from __future__ import annotations

import threading

import pytest

from gsavatar.utils.errors import SchemaError
from gsavatar.utils.jsonio import read_json
from gsavatar.utils.outdir import MARKER, claim_output_dir, output_kind


def test_a_marker_being_written_does_not_make_the_folder_foreign(tmp_path):
    d = tmp_path / "out"
    d.mkdir()
    temp = d / f".{MARKER}.k3j2l1.json"  # the name atomic_path gives the marker's temp file
    temp.write_text("")
    assert claim_output_dir(d, "dataset") == d
    assert read_json(d / MARKER) == {"format": "gsavatar-output", "kind": "dataset"}
    assert output_kind(d) == "dataset"


def test_a_users_file_beside_a_marker_temp_file_is_still_refused(tmp_path):
    d = tmp_path / "out"
    d.mkdir()
    (d / f".{MARKER}.k3j2l1.json").write_text("")
    (d / "notes.txt").write_text("mine")
    with pytest.raises(SchemaError, match="not empty"):
        claim_output_dir(d, "dataset")
    assert not (d / MARKER).exists() and (d / "notes.txt").read_text() == "mine"


def test_concurrent_claims_of_one_new_folder_all_succeed(tmp_path):
    errors: list[BaseException] = []

    def claim(d):
        try:
            claim_output_dir(d, "dataset")
        except BaseException as e:  # noqa: BLE001 - collected and asserted below
            errors.append(e)

    for i in range(40):
        d = tmp_path / f"out{i}"
        threads = [threading.Thread(target=claim, args=(d,)) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert output_kind(d) == "dataset"
    assert errors == []
