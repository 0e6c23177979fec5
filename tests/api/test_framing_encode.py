"""``encode`` passes lists of finite floats through as they are: the same bytes as before."""

from __future__ import annotations

import json
import math
from enum import Enum
from typing import Any

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from jtc_hw.api.framing import encode


def reference(obj: Any) -> Any:
    """``_jsonable`` as it was, one call per value."""
    if obj is None or isinstance(obj, (str, bool)):
        return obj
    if isinstance(obj, Enum):
        return reference(obj.value)
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): reference(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [reference(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return reference(obj.tolist())
    if isinstance(obj, np.generic):
        return reference(obj.item())
    raise TypeError(obj)


leaf = st.one_of(
    st.floats(),  # NaN and infinities included
    st.floats(allow_nan=False, allow_infinity=False),
    st.floats(-1e308, 1e308).map(lambda x: x * 10.0),  # finite values whose sum overflows
    st.integers(),
    st.booleans(),
    st.none(),
    st.text(max_size=3),
    st.sampled_from([np.float64(1.5), np.float32(2.5), np.int64(3), np.float64("nan")]),
)
values = st.recursive(
    leaf,
    lambda inner: st.one_of(
        st.lists(inner, max_size=6),
        st.lists(inner, max_size=6).map(tuple),
        st.dictionaries(st.text(max_size=3), inner, max_size=4),
    ),
    max_leaves=30,
)


@settings(max_examples=500, deadline=None)
@given(obj=values)
def test_same_bytes_as_value_by_value(obj: Any) -> None:
    expected = json.dumps(
        reference(obj), allow_nan=False, ensure_ascii=False, separators=(",", ":")
    ).encode() + b"\n"
    assert encode(obj) == expected
