"""`P/heightmap/live` bytes: the SLHM height map plus sequence, metadata and bit layers."""

from __future__ import annotations

import numpy as np
import pytest

from silo_agent.telemetry.heightmap_codec import (
    HeightMapFormatError,
    decode_heightmap,
    decode_heightmap_with_ids,
    decode_live_heightmap,
    encode_heightmap,
    encode_live_heightmap,
)
from tests.support.mqtt import realistic_heightmap


def layers(shape: tuple[int, int]) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    changed = rng.random(shape) < 0.05
    held = np.zeros(shape, dtype=bool)
    held[10:40, 20:50] = True
    return {"changed": changed, "held": held}


def test_live_map_round_trips_with_sequence_meta_and_layers():
    hm = realistic_heightmap(rows=60, cols=90)
    masks = layers(hm.shape)
    meta = {"robots": [{"x": 1.25, "y": -0.5, "top_z": 1.1, "radius_m": 0.36, "cells": 700}]}
    data = encode_live_heightmap(hm, "silo-d-live-1", 2**32 + 7, meta, masks)
    live = decode_live_heightmap(data)
    assert live.sequence == 7  # uint32 wraps
    assert live.session_id == "silo-d-live-1"
    assert live.meta == meta
    assert set(live.layers) == {"changed", "held"}
    for name, mask in masks.items():
        np.testing.assert_array_equal(live.layers[name], mask)
    known = np.isfinite(hm.heights)
    np.testing.assert_allclose(live.heightmap.heights[known], hm.heights[known], atol=5e-4)
    np.testing.assert_array_equal(live.heightmap.observed, hm.observed)


def test_a_plain_decoder_reads_the_live_maps_heights():
    """Same SLHM format: a robot that only knows P/heightmap gets the live heights."""
    hm = realistic_heightmap(rows=40, cols=50)
    data = encode_live_heightmap(hm, "s", 1, {}, layers(hm.shape))
    plain, session, frame = decode_heightmap_with_ids(data)
    assert session == "s" and frame == "silo"
    np.testing.assert_array_equal(plain.heights, decode_live_heightmap(data).heightmap.heights)


def test_errors_name_the_problem():
    hm = realistic_heightmap(rows=20, cols=30)
    full_scan = encode_heightmap(hm, "scan-1")
    with pytest.raises(HeightMapFormatError, match="not a live height map"):
        decode_live_heightmap(full_scan)
    with pytest.raises(HeightMapFormatError, match="length mismatch"):
        decode_heightmap(full_scan + b"\0")  # a full-scan map still has no tail
    live = encode_live_heightmap(hm, "s", 1, {"a": 1}, layers(hm.shape))
    with pytest.raises(HeightMapFormatError, match="live map"):
        decode_live_heightmap(live[:-3])
    with pytest.raises(ValueError, match="layer 'changed'"):
        encode_live_heightmap(hm, "s", 1, {}, {"changed": np.zeros((3, 3), bool)})
