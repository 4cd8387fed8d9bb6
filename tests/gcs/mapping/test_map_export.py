"""Map export: ROS map_server PGM + YAML and PNG."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from gcs.mapping.map_export import map_image, read_pgm_yaml, write_pgm_yaml, write_png
from gcs.mapping.rasterization import FREE, OCCUPIED, UNKNOWN, OccupancyMap


def sample_map() -> OccupancyMap:
    rng = np.random.default_rng(0)
    values = rng.choice(np.array([UNKNOWN, FREE, OCCUPIED], dtype=np.int8), size=(30, 45))
    values[-1, 0] = OCCUPIED  # the top-left pixel of the image (largest y, smallest x)
    values[0, 0] = FREE  # the bottom-left pixel
    return OccupancyMap(values, (-12.3, 4.5), 0.1)


def test_pgm_yaml_round_trip_and_map_server_fields(tmp_path: Path) -> None:
    m = sample_map()
    pgm, yml = write_pgm_yaml(m, tmp_path / "maps" / "phase1")
    assert pgm.name == "phase1.pgm" and yml.name == "phase1.yaml"
    doc = yaml.safe_load(yml.read_text())
    assert doc["image"] == "phase1.pgm"
    assert doc["mode"] == "trinary" and doc["negate"] == 0
    assert doc["resolution"] == pytest.approx(0.1)
    assert doc["origin"] == pytest.approx([-12.3, 4.5, 0.0])
    assert 0 < doc["free_thresh"] < doc["occupied_thresh"] < 1
    raw = pgm.read_bytes()
    assert raw.startswith(b"P5\n45 30\n255\n")
    back = read_pgm_yaml(yml)
    assert np.array_equal(back.values, m.values)
    assert back.origin_in_map == pytest.approx(m.origin_in_map)
    assert back.resolution_m == pytest.approx(0.1)


def test_image_is_north_up_with_map_saver_pixels(tmp_path: Path) -> None:
    m = sample_map()
    img = map_image(m)
    assert img[0, 0] == 0  # occupied, largest y
    assert img[-1, 0] == 254  # free, smallest y
    assert set(np.unique(img)) <= {0, 205, 254}
    png = write_png(m, tmp_path / "phase1.png")
    assert np.array_equal(cv2.imread(str(png), cv2.IMREAD_UNCHANGED), img)


def test_bad_maps_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="empty"):
        write_png(
            OccupancyMap(np.zeros((0, 0), dtype=np.int8), (0.0, 0.0), 0.1), tmp_path / "e.png"
        )
    bad = OccupancyMap(np.full((2, 2), 50, dtype=np.int8), (0.0, 0.0), 0.1)
    with pytest.raises(ValueError, match="found 50"):
        write_pgm_yaml(bad, tmp_path / "bad")
    (tmp_path / "x.yaml").write_text("image: x.pgm\nresolution: 0.1\n")
    with pytest.raises(ValueError, match="origin"):
        read_pgm_yaml(tmp_path / "x.yaml")
