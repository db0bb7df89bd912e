"""What an .rrd recording holds, read back row by row (rerun's chunk reader): the tests of the
viewer and of the whole flight check entities, capture times and the last value a viewer shows."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa
from rerun.chunk import RrdReader


@dataclass
class Row:
    entity: str
    utime: int | None      # None: static
    row_id: bytes          # rerun's row ids grow with logging order
    components: dict[str, Any]


def read_rows(path: Path) -> list[Row]:
    rows = []
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        names = batch.schema.names
        utimes = (batch.column("capture_time").cast(pa.int64()).to_numpy() // 1000
                  if "capture_time" in names else [None] * batch.num_rows)
        data = {name: batch.column(name).to_pylist() for name in names
                if ":" in name and not name.startswith("rerun.")}
        for i in range(batch.num_rows):
            rows.append(Row(chunk.entity_path.lstrip("/"),
                            None if utimes[i] is None else int(utimes[i]),
                            batch.column("rerun.controls.RowId")[i].as_py(),
                            {name: values[i] for name, values in data.items()}))
    return rows


def latest(rows: list[Row], entity: str, component: str) -> Any:
    """ENTITY's last value of COMPONENT, as a viewer at the end of the recording shows it."""
    candidates = [r for r in rows if r.entity == entity and component in r.components]
    assert candidates, f"nothing logged to {entity} {component}"
    return max(candidates, key=lambda r: (r.utime, r.row_id)).components[component]
