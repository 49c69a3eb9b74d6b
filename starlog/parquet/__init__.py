"""Parquet export: starlog's tables (one per channel family, their columns declared in ``schemas/tables.json``)
and any other channel or image channel flattened into a table.

:mod:`starlog.parquet.tables` writes the families a log has channels for; :mod:`starlog.parquet.channels`
flattens any JSON, protobuf, ROS 1 or ROS 2 channel (and any image channel's frame list) into rows.
"""

from starlog.parquet.tables import TABLES, TableSpec, arrow_schema, export_log, table_columns

__all__ = ["TABLES", "TableSpec", "arrow_schema", "export_log", "table_columns"]
