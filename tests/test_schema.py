"""coin_cl.schema: one error type whose one-line message names the file, the field and the fix."""

import json

import pytest

from coin_cl.schema import MANIFEST, PLAN, SCENE, Field, Obj, SchemaError, inside, parse

SPEC = Obj({"n": Field(int, lo=0, hi=10), "x": Field(float, required=False, nullable=True, lo=0),
            "kind": Field(str, choices=("a", "b")), "rows": Field(list, items=Field(int, lo=0))})  # fmt: skip


def _write(tmp_path, doc, raw=None):
    p = tmp_path / "f.json"
    p.write_text(raw if raw is not None else json.dumps(doc))
    return p


@pytest.mark.parametrize(
    ("doc", "raw", "field"),
    [
        (None, "{not json", "not valid JSON"),
        ([1, 2], None, "expected an object"),
        ({"n": 1, "kind": "a", "rows": [], "extra": 1}, None, "unknown key extra"),
        ({"kind": "a", "rows": []}, None, "n is missing"),
        ({"n": 11, "kind": "a", "rows": []}, None, "n is 11, outside 0..10"),
        ({"n": True, "kind": "a", "rows": []}, None, "n is true, expected an integer"),
        ({"n": 1, "kind": "c", "rows": []}, None, 'kind is "c", expected one of'),
        ({"n": 1, "kind": "a", "rows": [1, -2]}, None, "rows[1] is -2"),
        (None, '{"n": 1, "kind": "a", "rows": [], "x": NaN}', "x is nan, outside"),
    ],
)
def test_every_mismatch_is_one_line_naming_file_and_field(tmp_path, doc, raw, field):
    p = _write(tmp_path, doc, raw)
    with pytest.raises(SchemaError) as e:
        parse(p, SPEC, "delete it")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{p}: ") and field in msg and msg.endswith("; delete it")


def test_a_matching_document_is_returned_as_is(tmp_path):
    doc = {"n": 3, "kind": "b", "rows": [0, 4], "x": None}
    assert parse(_write(tmp_path, doc), SPEC, "") == doc


def test_the_runners_own_files_match_their_specs(tmp_path):
    man = {"key": "ab", "settings": {"a": 1}, "outputs": {"x.png": "00"}, "result": {}, "seconds": 1.5}
    assert parse(_write(tmp_path, man), MANIFEST, "") == man
    with pytest.raises(SchemaError, match="seconds is -1"):
        parse(_write(tmp_path, {**man, "seconds": -1}), MANIFEST, "")
    with pytest.raises(SchemaError, match="steps.refgs is 1000000000, outside 0..10000000"):
        parse(
            _write(tmp_path, {"steps": {"refgs": 10**9, "ted_finetune": 1, "ted_adversarial": 1}}), PLAN, ""
        )
    with pytest.raises(SchemaError, match="views is 3, expected a list"):
        parse(_write(tmp_path, {"format": "coin-cl scene", "version": 1, "views": 3}), SCENE, "")


def test_a_path_must_stay_inside_its_folder(tmp_path):
    (tmp_path / "s" / "images").mkdir(parents=True)
    assert inside(tmp_path / "s", "images/a.png", tmp_path / "s" / "scene.json", "k") == (
        tmp_path / "s" / "images" / "a.png"
    )
    for bad in ("../x.png", "/etc/passwd", "images/../../x.png"):
        with pytest.raises(SchemaError, match="leads outside the scene folder"):
            inside(tmp_path / "s", bad, tmp_path / "s" / "scene.json", "views[0].image")
    (tmp_path / "s" / "link").symlink_to(tmp_path)  # a symlink out counts as outside
    with pytest.raises(SchemaError, match="views\\[0\\].image is 'link/x.png'"):
        inside(tmp_path / "s", "link/x.png", tmp_path / "s" / "scene.json", "views[0].image")
