"""Comparing model descriptions: what a resumed fit keeps from its checkpoint."""

import math

from hypothesis import given
from hypothesis import strategies as st

from fields.description_diff import description_differences


def test_equal_descriptions_have_no_differences():
    d = {"field": {"resolutions": [16, 32], "aabb_lo": (-1.5, 2.0, 0.0), "mask": None, "view": False},
         "ground_z": 0.25}
    same = {"field": {"resolutions": (16, 32), "aabb_lo": [-1.5, 2, 0], "mask": None, "view": False},
            "ground_z": 0.25 * (1 + 1e-12)}
    assert description_differences(d, same) == {}


def test_differences_name_the_leaf_and_keep_sequences_whole():
    saved = {"field": {"encoding": "hash", "resolutions": [16, 32, 64], "features": 2},
             "sampler": {"kind": "occupancy"}, "old_only": 1}
    fresh = {"field": {"encoding": "planes", "resolutions": [16, 40, 64], "features": 2},
             "sampler": {"kind": "occupancy"}, "new_only": True}
    assert description_differences(saved, fresh) == {
        "field.encoding": ("hash", "planes"),
        "field.resolutions": ([16, 32, 64], [16, 40, 64]),
        "new_only": (None, True),
        "old_only": (1, None),
    }
    assert description_differences({"r": [1, 2]}, {"r": [1, 2, 3]}) == {"r": ([1, 2], [1, 2, 3])}


def test_hard_leaves_bool_against_int_nan_and_none():
    assert description_differences({"a": True}, {"a": 1}) == {"a": (True, 1)}
    assert description_differences({"a": math.nan}, {"a": math.nan}) == {}
    assert description_differences({"a": math.nan}, {"a": 0.0}) != {}
    assert description_differences({"a": None}, {"a": 0}) == {"a": (None, 0)}
    assert description_differences({"a": 0.0}, {"a": 1e-300}) == {"a": (0.0, 1e-300)}


leaves = st.one_of(st.none(), st.booleans(), st.integers(-5, 5), st.floats(allow_nan=False), st.text(max_size=3))
trees = st.recursive(leaves, lambda inner: st.one_of(st.lists(inner, max_size=3),
                                                    st.dictionaries(st.text(max_size=2), inner, max_size=3)),
                     max_leaves=10)


@given(trees)
def test_a_description_equals_itself(tree):
    assert description_differences({"d": tree}, {"d": tree}) == {}


@given(trees, trees)
def test_differences_are_symmetric(a, b):
    ab = description_differences({"d": a}, {"d": b})
    ba = description_differences({"d": b}, {"d": a})
    assert set(ab) == set(ba) and all(ab[k] == tuple(reversed(ba[k])) for k in ab)
