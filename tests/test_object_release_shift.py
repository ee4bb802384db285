"""The object query's release shift (policy/object_query.py): read from the manifest, checked, added to the
locator's release point only."""

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


def _given(manifest):
    q = ObjectQuery(_Located(object_query_spec(manifest)), "put the red block in the open drawer", "drawer_stow")
    return q, q.inputs({}, None, 0)


def test_the_release_point_given_is_the_locators_plus_the_manifests_shift():
    _, plain = _given(MANIFEST)
    np.testing.assert_allclose(plain["release"], [*DROP, 1.0], atol=1e-6)  # none: the locator's own
    shifted = {**MANIFEST, "object_query": {**MANIFEST["object_query"], "release_shift_m": [0.0, -0.03, 0.01]}}
    q, given = _given(shifted)
    np.testing.assert_allclose(given["release"], [DROP[0], DROP[1] - 0.03, DROP[2] + 0.01, 1.0], atol=1e-6)
    np.testing.assert_allclose(given["grasp"], [*OBJECT, 1.0], atol=1e-6)  # the object where it lies
    np.testing.assert_allclose(q.points, [OBJECT, DROP], atol=1e-6)  # the answer recorded as the locator gave it
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
