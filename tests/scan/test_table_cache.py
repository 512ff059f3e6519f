"""One projection table per (scene, pitch) and process (clrecon.scan.table.cached_projection_table):
the same object for equal scenes, bit-identical to projection_table, read-only, another entry for
another pitch or scene, and a recorded trace changed on disk is another scan."""

import numpy as np
import pytest

from clrecon.config.scene import load_scene
from clrecon.scan import signals
from clrecon.scan.table import ProjectionTable, cached_projection_table, projection_table


def _same(a: ProjectionTable, b: ProjectionTable) -> bool:
    return all(np.array_equal(getattr(a, c), getattr(b, c)) and getattr(a, c).dtype == getattr(b, c).dtype
               for c in ProjectionTable.COLUMNS) and a.views_per_rotation == b.views_per_rotation


def test_equal_scenes_share_one_table_identical_to_a_fresh_one():
    a = cached_projection_table(load_scene("tiny"), 0.1)
    b = cached_projection_table(load_scene("tiny"), 0.1)  # another object, the same scene
    assert a is b and _same(a, projection_table(load_scene("tiny"), 0.1))
    assert cached_projection_table(load_scene("tiny"), 0.2) is not a
    other = load_scene("tiny").replace(scan={"start_angle_deg": 10.0})
    assert not np.array_equal(cached_projection_table(other, 0.1).angle_rad, a.angle_rad)


def test_its_columns_are_read_only():
    t = cached_projection_table(load_scene("tiny"), 0.1)
    with pytest.raises(ValueError, match="read-only"):
        t.source_z_mm[0] = 0.0
    sub = t.take(np.arange(3))  # a sub-table is the caller's own
    z0 = float(t.source_z_mm[0])
    sub.source_z_mm[0] = z0 + 1.0
    assert t.source_z_mm[0] == z0


def _write_trace(path, scene, scale: float) -> None:
    tr = signals.respiratory_trace(scene, step_s=0.04)
    rows = "".join(f"{x:.6f},{scale * a:.7f},1\n" for x, a in zip(tr.time_s, tr.raw, strict=True))
    path.write_text("time_s,amplitude,valid\n" + rows)


def test_a_trace_changed_on_disk_is_another_scan(tmp_path):
    base = load_scene("tiny")
    path = tmp_path / "b.csv"
    _write_trace(path, base, 1.0)
    scene = base.replace(signals={"breathing_trace": str(path)})
    first = cached_projection_table(scene, 0.1)
    _write_trace(path, base, -1.0)  # the same path, the breathing upside down
    second = cached_projection_table(scene, 0.1)
    assert second is not first and _same(second, projection_table(scene, 0.1))
    assert not np.array_equal(first.resp_amplitude, second.resp_amplitude)
