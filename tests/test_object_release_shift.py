"""The object query's release point (policy/object_query.py): the manifest's shift, read, checked and added to the
locator's release point only; and the families that keep it for the grasp cycles after the query's."""

import numpy as np
import pytest

from policy.object_query import ObjectQuery, object_query_spec, parse_release_shift

MANIFEST = {"tasks": ["drawer_put", "drawer_stow"], "grasp_input": True,
            "object_query": {"families": ["drawer_put", "drawer_stow"], "stage": 1, "ticks": 1,
                             "family_stage": {"drawer_stow": 0}}}
OBJECT, DROP = [0.2, 0.3, 0.03], [-0.18, 0.49, 0.04]


class _Located:
    """A bundle stand-in for ObjectQuery: the locator always answers OBJECT and DROP."""

    def __init__(self, spec):
        self.object_query = spec

    def embed(self, text):
        return np.zeros(384, np.float32)

    def object_points(self, images, proprio, emb):
        return np.array([OBJECT, DROP], np.float32)


def _query(manifest, family="drawer_stow"):
    return ObjectQuery(_Located(object_query_spec(manifest)), "put the red block in the open drawer", family)


def _given(manifest):
    q = _query(manifest)
    return q, q.inputs({}, None, 0)


def test_the_release_point_given_is_the_locators_plus_the_manifests_shift():
    _, plain = _given(MANIFEST)
    np.testing.assert_allclose(plain["release"], [*DROP, 1.0], atol=1e-6)  # none: the locator's own
    shifted = {**MANIFEST, "object_query": {**MANIFEST["object_query"], "release_shift_m": [0.0, -0.03, 0.01]}}
    q, given = _given(shifted)
    np.testing.assert_allclose(given["release"], [DROP[0], DROP[1] - 0.03, DROP[2] + 0.01, 1.0], atol=1e-6)
    np.testing.assert_allclose(given["grasp"], [*OBJECT, 1.0], atol=1e-6)  # the object where it lies
    np.testing.assert_allclose(q.points, [OBJECT, DROP], atol=1e-6)  # the answer recorded as the locator gave it
    np.testing.assert_array_equal(q.drop, given["release"][:3])  # the drop the runtime's release guard measures from
    again = q.inputs({}, None, 0)
    np.testing.assert_allclose(again["release"], given["release"], atol=1e-6)  # added once per inference, not held


@pytest.mark.parametrize("bad", [[0.0, -0.03], [0.0, -0.2, 0.0], [0.0, float("nan"), 0.0], ["0", 0.0, 0.0],
                                 [True, 0.0, 0.0], 0.03])
def test_a_manifest_release_shift_out_of_range_is_refused_naming_the_field(bad):
    wrong = {**MANIFEST, "object_query": {**MANIFEST["object_query"], "release_shift_m": bad}}
    with pytest.raises(ValueError, match=r"object_query\.release_shift_m .*within 0\.1 m"):
        object_query_spec(wrong)


def test_the_export_option_parses_three_numbers_within_the_limit():
    assert parse_release_shift("0,-0.03,0") == (0.0, -0.03, 0.0)
    for bad in ("0,-0.03", "a,b,c", "0,-0.3,0"):
        with pytest.raises(ValueError, match="--object-release-shift"):
            parse_release_shift(bad)


def test_a_family_that_keeps_the_drop_gets_it_alone_in_its_later_grasp_cycles():
    kept = {**MANIFEST, "object_query": {**MANIFEST["object_query"], "keep_release": ["drawer_stow"],
                                         "release_shift_m": [0.0, -0.03, 0.0]}}
    stow = _query(kept)
    assert set(stow.inputs({}, None, 0)) == {"grasp", "release"}  # its own cycle: both points
    later = stow.inputs({}, None, 1)  # the object let go elsewhere and taken again: the drop, not the old object
    assert set(later) == {"release"}
    np.testing.assert_allclose(later["release"], [DROP[0], DROP[1] - 0.03, DROP[2], 1.0], atol=1e-6)
    assert _query(MANIFEST).inputs({}, None, 1) == {}  # not kept: the head's own, as before
    put = _query(kept, "drawer_put")  # its next cycle is the handle: nothing kept, nothing before its own cycle
    assert put.inputs({}, None, 0) == {} and put.inputs({}, None, 2) == {}
    assert set(put.inputs({}, None, 1)) == {"grasp", "release"}


@pytest.mark.parametrize("bad", [["pick_place"], "drawer_stow", [1], None])
def test_a_manifest_keep_release_of_a_family_the_query_does_not_serve_is_refused(bad):
    wrong = {**MANIFEST, "object_query": {**MANIFEST["object_query"], "keep_release": bad}}
    with pytest.raises(ValueError, match=r"object_query\.keep_release .*drawer_put, drawer_stow"):
        object_query_spec(wrong)
