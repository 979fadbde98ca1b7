"""An .rrd file read back with Rerun's own reader (``rerun.chunk.RrdReader``): tests, benchmarks, checks.

``RrdContents(path)`` loads the file's first recording into memory
(``RrdReader(path).stream().collect()``). ``rows(entity, component)`` gives the rows of one
entity that hold a component (``"Transform3D:translation"``, ``"Image:buffer"``, ...), in the
order they were logged, each with its instances and its time on every timeline (timestamps
as int nanoseconds). Entity paths are written as in ``services.viewer.layout``, without
Rerun's leading ``/``. ``views()`` lists the views of the blueprint sent last.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
from rerun.chunk import RrdReader

ROW_ID = "rerun.controls.RowId"


@dataclass(frozen=True)
class Row:
    """One logged row: the component's instances and the row's time on each timeline."""

    values: pa.Array
    times: dict[str, int]
    row_id: bytes

    def numbers(self) -> np.ndarray:
        """Every number in ``values``, flattened (an image's pixels, a translation's x, y, z)."""
        values = self.values
        while pa.types.is_list(values.type) or pa.types.is_fixed_size_list(values.type):
            values = values.flatten()
        return values.to_numpy(zero_copy_only=False)


class RrdContents:
    """The first recording of an .rrd file and its blueprints (see the module docstring)."""

    def __init__(self, path: Path | str):
        reader = RrdReader(path)
        self._reader = reader
        self._batches: dict[str, list[pa.RecordBatch]] = defaultdict(list)
        for chunk in reader.stream().collect().stream():
            self._batches[chunk.entity_path.lstrip("/")].append(chunk.to_record_batch())

    @property
    def entities(self) -> set[str]:
        return set(self._batches)

    def rows(self, entity: str, component: str) -> list[Row]:
        """The rows of ``entity`` holding ``component``, in logging order."""
        found = []
        for batch in self._batches.get(entity, []):
            if component not in batch.schema.names:
                continue
            timelines = [name for name in batch.schema.names if ":" not in name and name != ROW_ID]
            values, ids = batch.column(component), batch.column(ROW_ID).to_pylist()
            times = {name: batch.column(name).cast(pa.int64()).to_pylist() for name in timelines}
            found += [Row(values[i].values, {name: column[i] for name, column in times.items()}, ids[i])
                      for i in range(batch.num_rows) if values[i].is_valid]
        return sorted(found, key=lambda row: row.row_id)

    def views(self) -> list[tuple[str, str]]:
        """``(view class, origin)`` of each view in the last blueprint sent, e.g. ``("2D", "world/cam0/image")``."""
        latest: tuple[bytes, list[tuple[str, str]]] = (b"", [])
        for entry in self._reader.blueprints():  # one store per blueprint sent; row ids grow with time
            found, newest = [], b""
            for chunk in self._reader.stream(store=entry).collect().stream():
                batch = chunk.to_record_batch()
                newest = max(newest, *batch.column(ROW_ID).to_pylist())
                if "ViewBlueprint:space_origin" in batch.schema.names:
                    kinds = batch.column("ViewBlueprint:class_identifier").to_pylist()
                    origins = batch.column("ViewBlueprint:space_origin").to_pylist()
                    found += [(kind[0], origin[0]) for kind, origin in zip(kinds, origins, strict=True)]
            latest = max(latest, (newest, sorted(found)))
        return latest[1]
