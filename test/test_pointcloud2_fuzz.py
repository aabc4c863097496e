"""
Property-based fuzzing of the PointCloud2 decoder (cgags_ros.io.pointcloud2).

Every message, however malformed, decodes to a valid cloud or raises the module's typed
error (MalformedCloudError or EmptyCloudError), nothing else; a well-formed message of any
layout decodes to exactly the points it carries.
"""

from __future__ import annotations

import types

from cgags_ros.errors import EmptyCloudError, MalformedCloudError
from cgags_ros.io.pointcloud2 import pointcloud2_to_xyz
from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np

UINT32 = st.integers(0, 2**32 - 1)
SMALL = st.integers(0, 40)
FIELD_NAMES = st.sampled_from(['x', 'y', 'z', 'intensity', 'rgb', 'X', ''])
SETTINGS = settings(max_examples=400, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow])


def field(name, offset, datatype, count):
    return types.SimpleNamespace(name=name, offset=offset, datatype=datatype, count=count)


@st.composite
def malformed_messages(draw):
    """Draw a PointCloud2-shaped message with every header value fuzzed."""
    fields = draw(st.lists(st.builds(field, FIELD_NAMES, st.one_of(SMALL, UINT32),
                                     st.integers(0, 255), st.integers(0, 4)), max_size=6))
    if draw(st.booleans()):  # often give it x, y, z so decoding goes deeper
        fields += [field(a, draw(SMALL), draw(st.sampled_from([7, 8, 7, 2])), 1)
                   for a in 'xyz']
    height = draw(st.one_of(st.integers(0, 4), UINT32))
    width = draw(st.one_of(st.integers(0, 12), UINT32))
    point_step = draw(st.one_of(st.integers(0, 48), UINT32))
    row_step = draw(st.one_of(st.just(width * point_step), st.integers(0, 600), UINT32))
    if draw(st.booleans()) and height * row_step < 20_000:
        size = height * row_step + draw(st.sampled_from([0, 0, -1, 1, -7]))
    else:
        size = draw(st.integers(0, 3000))
    data = draw(st.binary(min_size=max(size, 0), max_size=max(size, 0)))
    return types.SimpleNamespace(height=height, width=width, fields=fields,
                                 is_bigendian=draw(st.booleans()), point_step=point_step,
                                 row_step=row_step, data=data, is_dense=draw(st.booleans()))


@st.composite
def near_valid_messages(draw):
    """Draw a valid x, y, z message with one or two header values or the data corrupted."""
    height, width = draw(st.integers(1, 4)), draw(st.integers(1, 12))
    datatype = draw(st.sampled_from([7, 8]))
    size = 4 if datatype == 7 else 8
    fields = [field(a, i * size, datatype, 1) for i, a in enumerate('xyz')]
    point_step = 3 * size + draw(st.integers(0, 8))
    row_step = width * point_step + draw(st.integers(0, 8))
    msg = types.SimpleNamespace(height=height, width=width, fields=fields,
                                is_bigendian=draw(st.booleans()), point_step=point_step,
                                row_step=row_step, is_dense=True,
                                data=draw(st.binary(min_size=height * row_step,
                                                    max_size=height * row_step)))
    for _ in range(draw(st.integers(1, 2))):
        what = draw(st.sampled_from(['height', 'width', 'point_step', 'row_step', 'data',
                                     'offset', 'datatype', 'count', 'drop_field', 'none']))
        if what in ('height', 'width', 'point_step', 'row_step'):
            setattr(msg, what, max(0, getattr(msg, what) + draw(st.integers(-9, 9))))
        elif what == 'data':
            msg.data = msg.data[:draw(st.integers(0, len(msg.data)))] + draw(st.binary())
        elif what in ('offset', 'datatype', 'count'):
            f = draw(st.sampled_from(fields))
            setattr(f, what, draw(st.integers(0, 40 if what == 'offset' else 9)))
        elif what == 'drop_field':
            fields.pop(draw(st.integers(0, len(fields) - 1)))
    return msg


@SETTINGS
@given(st.one_of(malformed_messages(), near_valid_messages()))
def test_any_message_decodes_or_raises_the_typed_error(msg):
    try:
        xyz = pointcloud2_to_xyz(msg, max_points=100_000)
    except (MalformedCloudError, EmptyCloudError) as exc:
        assert str(exc)  # says what is wrong
        return
    assert xyz.dtype == np.float64 and xyz.ndim == 2 and xyz.shape[1] == 3
    assert 0 < len(xyz) <= msg.height * msg.width
    assert np.isfinite(xyz).all()


@st.composite
def wellformed_messages(draw):
    """Draw a valid message of any layout, with the points it must decode to."""
    n_rows, width = draw(st.integers(1, 4)), draw(st.integers(1, 10))
    dtype = draw(st.sampled_from(['f4', 'f8']))
    order = draw(st.permutations('xyz'))
    size = 4 if dtype == 'f4' else 8
    gaps = [draw(st.integers(0, 5)) for _ in range(3)]
    offsets, pos = {}, draw(st.integers(0, 6))
    for axis, gap in zip(order, gaps):
        offsets[axis] = pos
        pos += size + gap
    point_step = pos + draw(st.integers(0, 6))
    row_step = width * point_step + draw(st.integers(0, 9))
    big = draw(st.booleans())
    values = draw(st.lists(st.floats(-1e6, 1e6, width=32), min_size=3 * n_rows * width,
                           max_size=3 * n_rows * width))
    points = np.array(values, dtype=np.float64).reshape(-1, 3)
    if draw(st.booleans()) and len(points) > 1:
        points[draw(st.integers(0, len(points) - 1)), 0] = np.nan  # dropped on decode
    buf = bytearray(draw(st.binary(min_size=n_rows * row_step, max_size=n_rows * row_step)))
    fmt = ('>' if big else '<') + dtype
    for k, p in enumerate(points):
        row, col = divmod(k, width)
        for axis_index, axis in enumerate('xyz'):
            start = row * row_step + col * point_step + offsets[axis]
            buf[start:start + size] = np.array(p[axis_index], dtype=fmt).tobytes()
    fields = [field(a, offsets[a], 7 if dtype == 'f4' else 8, 1) for a in order]
    msg = types.SimpleNamespace(height=n_rows, width=width, fields=fields, is_bigendian=big,
                                point_step=point_step, row_step=row_step, data=bytes(buf),
                                is_dense=False)
    return msg, points


@SETTINGS
@given(wellformed_messages())
def test_wellformed_message_of_any_layout_decodes_to_its_points(case):
    msg, points = case
    finite = np.isfinite(points).all(axis=1)
    if not finite.any():
        return
    xyz = pointcloud2_to_xyz(msg)
    np.testing.assert_array_equal(xyz, points[finite])
