"""Readers of formats that need a third-party library (installed with an extra): workbooks
(pandas with openpyxl, xlrd or odfpy), Parquet and Feather tables (pyarrow), National
Instruments TDMS (npTDMS), miniSEED (ObsPy)
and ROS bags (rosbags). Each gives an :class:`~accelcal.io._ArraySource` built by the same
layout rules as a DataFrame, so names, units, time and temperature columns are chosen as for
text; ``io`` imports this module only when it meets one of these files."""

from __future__ import annotations

import contextlib
import os
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ._core import CalibrationError
from .io import (
    _ArraySource,
    _auto_acc,
    _dataframe_source,
    _resolve_columns,
    _split_unit,
    _three,
)

#: SEED orientation codes of a triad, in the x, y, z order read (east, north, up first).
_SEED_TRIADS = ("ENZ", "12Z", "123", "UVW", "XYZ")


def _mseed_source(p: str, columns: Any, fs: float | None, time_column: Any) -> _ArraySource:
    """A miniSEED file (seismic digitisers and data loggers) through ObsPy: the three
    components of one accelerometer channel (SEED instrument code ``N``: ``HNE, HNN, HNZ``
    read as x, y, z), or the traces named in ``columns`` (ids ``NET.STA.LOC.CHA`` or channel
    codes). Segments of a trace are joined, gaps read as NaN (dropouts), and the components
    cut to their common span; the rate and ``t0`` come from the record headers."""
    try:
        # ObsPy's import reads entry points through an interface that importlib.metadata
        # deprecates (Python 3.10-3.11): a DeprecationWarning from ObsPy's own module, which
        # the default filters ignore (not hidden here: that would change the process-wide
        # filters, which is not thread-safe).
        import obspy
    except ImportError:
        raise CalibrationError(
            f"{p}: a miniSEED file; reading it needs ObsPy: pip install 'accelcal[seismic]' "
            "(or obspy)") from None
    try:
        st = obspy.read(p)
        st.merge(method=0, fill_value=None)  # gaps and disagreeing overlaps: masked
    except Exception as e:  # noqa: BLE001 - ObsPy raises many types
        raise CalibrationError(
            f"{p}: cannot read the miniSEED file: {type(e).__name__}: {e}") from None
    traces = {tr.id: tr for tr in st}
    if len(traces) < len(st):
        each = sorted(f"{tr.id} ({tr.stats.sampling_rate:g} Hz)" for tr in st)
        raise CalibrationError(f"{p}: traces of one id at different sample rates: {each}")
    ids = _mseed_triad(p, traces, columns)
    chosen = [traces[i] for i in ids]
    rates = {float(tr.stats.sampling_rate) for tr in chosen}
    if len(rates) != 1:
        raise CalibrationError(f"{p}: the traces {ids} have different sample rates "
                               f"({sorted(rates)} Hz): resample them to one rate first")
    rate = rates.pop()
    start = max(tr.stats.starttime for tr in chosen)
    end = min(tr.stats.endtime for tr in chosen)
    if end < start:
        raise CalibrationError(f"{p}: the traces {ids} do not overlap in time")
    n = int(round((end - start) * rate)) + 1
    cols: dict[str, NDArray[Any]] = {}
    for tr in chosen:
        i0 = int(round((start - tr.stats.starttime) * rate))
        a = np.ma.asarray(tr.data[i0:i0 + n]).astype(np.float64)
        cols[tr.id] = np.ma.filled(a, np.nan)
    src = _dataframe_source(_DictTable(cols), ids, fs, time_column, path=p,
                            meta={"sampling_rate": repr(rate)})
    lay = src.lay
    lay.t0_text = str(start.isoformat())
    gaps = sum(int(np.isnan(a).sum()) for a in cols.values())
    lay.notes.append(
        f"miniSEED traces {', '.join(ids)} (as x, y, z; counts unless the logger wrote physical "
        f"units), their common span from {start} to {end}"
        + (f"; {gaps} samples in gaps read as NaN (dropouts)" if gaps else ""))
    return src


def _mseed_triad(p: str, traces: dict[str, Any], columns: Any) -> list[str]:
    """The ids of the three traces to read: ``columns`` (ids or channel codes), else the one
    accelerometer triad (instrument code N) of the file."""
    if columns is not None:
        out = []
        for c in _three(columns, "traces"):
            hits = [i for i in traces if i == str(c) or traces[i].stats.channel == str(c)]
            if len(hits) != 1:
                raise CalibrationError(
                    f"{p}: {'no' if not hits else 'more than one'} trace named {c!r} "
                    f"(columns); the traces are {sorted(traces)}")
            out.append(hits[0])
        return out
    groups: dict[str, dict[str, str]] = {}
    for i in traces:
        groups.setdefault(i[:-1], {})[i[-1]] = i
    triads = [(k, [g[c] for c in order]) for k, g in groups.items() for order in _SEED_TRIADS
              if set(order) <= set(g)]
    acc = [t for t in triads if len(t[0]) >= 1 and t[0][-1] == "N"]  # ...HN? : accelerometer
    if len(acc) == 1:
        return acc[0][1]
    listed = sorted(traces)
    if len(acc) > 1:
        raise CalibrationError(
            f"{p}: {len(acc)} accelerometer triads ({'; '.join(','.join(t) for _, t in acc)}): "
            "calibrate one at a time, giving its three traces with columns=, e.g. "
            f"{','.join(acc[0][1])!r}")
    other = f" ({', '.join(','.join(t) for _, t in triads)}: not accelerometer channels - " \
        "SEED instrument code N - and a seismometer's velocity output does not see gravity)" \
        if triads else ""
    raise CalibrationError(
        f"{p}: no accelerometer triad among the traces {listed}{other}; give columns= (3 "
        "trace ids or channel codes) if three of them are an accelerometer's")


def _holds_triad(names: list[str], columns: Any, p: str) -> bool:
    """Whether a table (a sheet, a TDMS group) with these column names holds the
    accelerometer: the ``columns`` given, or a triad found by name."""
    with contextlib.suppress(CalibrationError):
        if columns is None:
            return _auto_acc(names, p) is not None
        _resolve_columns(columns, names, len(names), p)
        return True
    return False


def _tdms_source(p: str, columns: Any, fs: float | None, time_column: Any) -> _ArraySource:
    """A National Instruments TDMS file (LabVIEW's own format) through npTDMS: the first
    group whose channel names hold an accelerometer triad (or the ``columns`` given), its
    channels of the triad's length as columns (``unit_string`` as their unit), the rate from
    the channels' ``wf_increment`` and ``wf_start_time`` as ``t0``."""
    try:
        from nptdms import TdmsFile
    except ImportError:
        raise CalibrationError(
            f"{p}: a TDMS file (NI LabVIEW); reading it needs npTDMS: pip install "
            "'accelcal[tdms]' (or npTDMS), or export the channels as text") from None
    try:
        f = TdmsFile.read(p)
    except Exception as e:  # noqa: BLE001 - npTDMS has no error type of its own
        raise CalibrationError(f"{p}: cannot read the TDMS file: {type(e).__name__}: {e}") from None
    groups: list[tuple[str, dict[str, Any]]] = []  # group name, channels by column name
    for g in f.groups():
        chans = [c for c in g.channels() if len(c) and np.asarray(c[:1]).dtype.kind in "fiuM"]
        names = []
        for c in chans:
            unit = str(c.properties.get("unit_string", "") or "").strip()
            names.append(f"{c.name} [{unit}]" if unit and not _split_unit(c.name)[1] else c.name)
        groups.append((g.name, dict(zip(names, chans, strict=True))))
    if not groups:
        raise CalibrationError(f"{p}: cannot read the TDMS file: it holds no channels of "
                               "numbers (not a TDMS file, or an empty one)")
    pick = next((x for x in groups if _holds_triad(list(x[1]), columns, p)), None)
    if pick is None:
        listed = "; ".join(f"{g!r}: {', '.join(repr(n) for n in cs)}" for g, cs in groups)
        raise CalibrationError(
            f"{p}: no TDMS group holds an accelerometer triad by name (groups and channels: "
            f"{listed or 'none'}); give columns=[...] (3 channel names)")
    gname, by_name = pick
    names = list(by_name)
    acc = (_auto_acc(names, p) if columns is None
           else _resolve_columns(columns, names, len(names), p)) or [0, 1, 2]
    n = len(by_name[names[acc[0]]])
    table = {k: np.asarray(c[:]) for k, c in by_name.items() if len(c) == n}
    first = by_name[names[acc[0]]].properties
    inc = first.get("wf_increment")
    src = _dataframe_source(_DictTable(table), columns, fs, time_column, path=p,
                            meta={"wf_increment": repr(float(inc)),
                                  "sample_rate": repr(1.0 / float(inc))} if inc else None)
    lay = src.lay
    start = first.get("wf_start_time")
    if lay.time is None and start is not None:
        lay.t0_text = str(np.datetime_as_string(np.datetime64(start, "us")))
    if len(groups) > 1:
        lay.notes.append(f"the samples were read from the TDMS group {gname!r} (of "
                         f"{', '.join(repr(g) for g, _ in groups)})")
    return src


class _DictTable:
    """Named 1-D arrays of one length, as a table for :func:`_dataframe_source`."""

    def __init__(self, cols: dict[str, NDArray[Any]]) -> None:
        self.cols = cols
        self.columns = list(cols)

    def __getitem__(self, k: str) -> NDArray[Any]:
        return self.cols[k]


def _spreadsheet_source(p: str, columns: Any, fs: float | None,
                        time_column: Any) -> _ArraySource:
    """A workbook read through pandas (openpyxl, xlrd or odfpy): the first sheet whose column
    names hold an accelerometer triad, or hold ``columns`` when given (phyphox puts its
    samples in "Raw Data" beside metadata sheets); with neither, the first sheet."""
    try:
        import pandas as pd
    except ImportError:
        raise CalibrationError(
            f"{p}: a spreadsheet; reading it needs pandas and openpyxl (pip install pandas "
            "openpyxl), or export the sheet as CSV") from None
    try:
        sheets = pd.read_excel(p, sheet_name=None)
    except ImportError as e:
        raise CalibrationError(f"{p}: {e} (or export the sheet as CSV)") from None
    except (ValueError, OSError, KeyError, zipfile.BadZipFile) as e:
        raise CalibrationError(f"{p}: cannot read the spreadsheet: {e}") from None
    if not sheets:
        raise CalibrationError(f"{p}: the workbook has no sheets")

    name, df = next(((k, v) for k, v in sheets.items()
                     if _holds_triad([str(c) for c in v.columns], columns, p)),
                    next(iter(sheets.items())))
    src = _dataframe_source(df, columns, fs, time_column, path=p)
    if len(sheets) > 1:
        src.lay.notes.append(f"the samples were read from the sheet {name!r} (of "
                             f"{', '.join(repr(k) for k in sheets)})")
    return src


def _arrow_source(p: str, columns: Any, fs: float | None, time_column: Any) -> _ArraySource:
    """A Parquet or Feather (Arrow IPC) table read through pyarrow and pandas, its columns
    chosen by name as from a header (a timestamp column is a time column)."""
    try:
        import pandas  # noqa: F401 - to_pandas needs it
        import pyarrow.feather as feather
        import pyarrow.parquet as parquet
    except ImportError:
        raise CalibrationError(
            f"{p}: a Parquet/Feather table; reading it needs pyarrow and pandas: pip install "
            "'accelcal[parquet]'") from None
    low = p.lower()
    try:
        table = (parquet.read_table(p) if low.endswith((".parquet", ".pq"))
                 else feather.read_table(p))
        df = table.to_pandas()
    except (OSError, ValueError) as e:  # pyarrow's ArrowInvalid is a ValueError
        kind = "Parquet" if low.endswith((".parquet", ".pq")) else "Feather"
        raise CalibrationError(f"{p}: cannot read the {kind} file: {e}") from None
    return _dataframe_source(df, columns, fs, time_column, path=p)


def is_rosbag(p: str) -> bool:
    """A ROS 1 ``.bag`` file, a ROS 2 bag folder (``metadata.yaml`` beside its storage) or
    that folder's ``.db3`` / ``.mcap`` file."""
    low = p.lower()
    if low.endswith(".bag"):
        return True
    if os.path.isdir(p):
        return os.path.isfile(os.path.join(p, "metadata.yaml"))
    return low.endswith((".db3", ".mcap")) and os.path.isfile(
        os.path.join(os.path.dirname(os.path.abspath(p)), "metadata.yaml"))


_IMU = "sensor_msgs/msg/Imu"


def _rosbag_source(p: str, columns: Any, fs: float | None, time_column: Any) -> _ArraySource:
    """A ROS bag through rosbags (no ROS installation needed): the ``sensor_msgs/Imu``
    messages of one topic, their ``linear_acceleration`` (which includes gravity: REP 145)
    as x, y, z in m/s^2 and their header stamps as the time (the bag's own receive times when
    the driver leaves the stamps unset). ``columns="/topic"`` picks the topic when the bag
    holds several."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise CalibrationError(
            f"{p}: a ROS bag; reading it needs rosbags: pip install 'accelcal[ros]' (or "
            "rosbags)") from None
    path = os.path.abspath(p)
    if os.path.isfile(path) and not path.lower().endswith(".bag"):
        path = os.path.dirname(path)  # a ROS 2 bag's storage file: its folder
    try:
        with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
            imu = [c for c in r.connections if c.msgtype == _IMU]
            counts: dict[str, int] = {}
            for c in imu:
                counts[c.topic] = counts.get(c.topic, 0) + int(c.msgcount)
            topic = _ros_topic(p, counts, columns, {c.topic: c.msgtype for c in r.connections})
            conns = [c for c in imu if c.topic == topic]
            n = counts[topic]
            acc = np.empty((n, 3))
            stamp = np.empty(n)
            received = np.empty(n)
            i = 0
            for conn, t_ns, raw in r.messages(connections=conns):
                m: Any = r.deserialize(raw, conn.msgtype)
                la, hs = m.linear_acceleration, m.header.stamp
                acc[i] = (la.x, la.y, la.z)
                stamp[i] = hs.sec + 1e-9 * hs.nanosec
                received[i] = 1e-9 * t_ns
                i += 1
    except CalibrationError:
        raise
    except Exception as e:  # noqa: BLE001 - rosbags raises many types
        raise CalibrationError(f"{p}: cannot read the ROS bag: {type(e).__name__}: {e}") from None
    acc, stamp, received = acc[:i], stamp[:i], received[:i]
    if i == 0:
        raise CalibrationError(f"{p}: the topic {topic} holds no messages")
    notes = [f"ROS topic {topic}: {i} sensor_msgs/Imu messages; linear_acceleration (which "
             "includes gravity, REP 145) read as x, y, z in m/s^2"]
    t = stamp
    if i > 1 and not bool(np.all(np.diff(stamp) > 0)):
        t = received
        notes.append("the header stamps do not increase (unset by the driver?): the bag's "
                     "receive times are the time")
    cols = {"t [s]": t - t[0], "ax [m/s^2]": acc[:, 0], "ay [m/s^2]": acc[:, 1],
            "az [m/s^2]": acc[:, 2]}
    src = _dataframe_source(_DictTable(cols), None, fs, time_column, path=p)
    src.lay.notes = notes + src.lay.notes
    src.lay.t0_text = str(np.datetime_as_string(np.datetime64(int(round(t[0] * 1e6)), "us")))
    return src


def _ros_topic(p: str, counts: dict[str, int], columns: Any, types: dict[str, str]) -> str:
    """The IMU topic to read: ``columns`` when it names one, else the only one."""
    listed = ", ".join(f"{k} ({v} messages)" for k, v in sorted(counts.items()))
    if isinstance(columns, str) and columns.startswith("/"):
        if columns not in counts:
            raise CalibrationError(
                f"{p}: no sensor_msgs/Imu topic {columns!r} in the bag (its IMU topics: "
                f"{listed or 'none'})")
        return columns
    if columns is not None:
        raise CalibrationError(f"{p}: in a ROS bag, columns= names the IMU topic (e.g. "
                               f"'/imu/data'); got {columns!r}")
    if len(counts) == 1:
        return next(iter(counts))
    if not counts:
        others = ", ".join(f"{k} ({v})" for k, v in sorted(types.items()))
        raise CalibrationError(f"{p}: no sensor_msgs/Imu topic in the bag (its topics: "
                               f"{others or 'none'})")
    raise CalibrationError(f"{p}: {len(counts)} IMU topics ({listed}): give the one to "
                           "calibrate with columns=, e.g. " + repr(min(counts)))


#: kind (as ``io._kind`` names it) -> reader.
SOURCES: dict[str, Callable[[str, Any, float | None, Any], _ArraySource]] = {
    "sheet": _spreadsheet_source,
    "arrow": _arrow_source,
    "tdms": _tdms_source,
    "mseed": _mseed_source,
    "rosbag": _rosbag_source,
}
