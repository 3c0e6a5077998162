"""Where caches are kept: a SQLite file (``store``) or a PostgreSQL server shared by
replicas (``pgstore``), their records and the index files beside them."""
