"""The database: ``db`` (engines, transactions, migrations), ``models`` (the study's tables),
``replica_models`` (the platform replicas' tables) and ``records`` (rows on the request path,
with SQLAlchemy Core)."""
