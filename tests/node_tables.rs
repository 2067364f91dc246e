//! The conformance suite of the DICOM node's tables (rules, rule runs, deliveries, the instance index), run
//! on both job databases: SQLite (the default) and PostgreSQL (on a throwaway cluster; skipped with one line
//! where PostgreSQL is not installed, unless `CTRECON_REQUIRE_PEERS=1`).

use ctrecon::jobs::{Database, Db};

mod sqlite {
    use super::*;

    /// A fresh database in a directory that lives as long as the test process.
    async fn fresh() -> Database {
        let dir = tempfile::tempdir().expect("temp dir").keep();
        Database::from(
            Db::open(&dir.join("ctrecon.sqlite"))
                .await
                .expect("database"),
        )
    }

    ctrecon::node_tables_conformance!(fresh());
}

use crate::cluster;

mod postgres {
    use super::*;
    use ctrecon::jobs::PgDb;

    /// A fresh database on the throwaway cluster, or `None` (one skip line) without PostgreSQL.
    async fn fresh() -> Option<Database> {
        let url = cluster::database_url("node_tables::postgres")?;
        Some(Database::from(
            PgDb::open(&url, std::time::Duration::from_secs(10))
                .await
                .expect("database"),
        ))
    }

    ctrecon::node_tables_conformance!(optional fresh());
}
