//! What really differs between the two databases, as SQL fragments the shared statements splice in. Every
//! other statement of the adapter is one text both run. The rest of the seam is in `driver` (a write
//! transaction: `BEGIN IMMEDIATE` on SQLite; advisory locks and `NOTIFY`, which are nothing on SQLite) and
//! in the schemas (`migrations/` and `migrations/postgres/`: `INTEGER`/`BIGINT`, `rowid`/`BIGSERIAL`).

/// The SQL dialect of the job database.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dialect {
    /// SQLite in the data directory: one process owns it, and a write transaction holds the only write
    /// lock.
    Sqlite,
    /// PostgreSQL, shared by several processes: rows are locked one by one.
    Postgres,
}

impl Dialect {
    /// Whether other processes may use the database at the same time.
    pub fn is_shared(self) -> bool {
        self == Dialect::Postgres
    }

    /// The end of a `SELECT` that locks the rows it picks, skipping rows another transaction holds (so that
    /// two workers claim different rows instead of waiting for each other). Nothing on SQLite, where the
    /// transaction already holds the one write lock.
    pub fn skip_locked(self) -> &'static str {
        match self {
            Dialect::Sqlite => "",
            Dialect::Postgres => " FOR UPDATE SKIP LOCKED",
        }
    }

    /// The end of a `SELECT` that locks the rows it reads until the transaction ends (nothing on SQLite).
    pub fn for_update(self) -> &'static str {
        match self {
            Dialect::Sqlite => "",
            Dialect::Postgres => " FOR UPDATE",
        }
    }

    /// A subquery of the strings of the JSON array bound to parameter `$n` (a list bound as one value), for
    /// `x IN …`.
    pub fn json_strings(self, n: u32) -> String {
        match self {
            Dialect::Sqlite => format!("(SELECT value FROM json_each(${n}))"),
            Dialect::Postgres => format!("(SELECT jsonb_array_elements_text(${n}::jsonb))"),
        }
    }

    /// The column that orders rows of `upload_files` as they were inserted.
    pub fn insertion_order(self) -> &'static str {
        match self {
            Dialect::Sqlite => "rowid",
            Dialect::Postgres => "seq",
        }
    }

    /// The columns of a job summary: the job's own, whether its result has metrics (`has_metrics`), and its
    /// products' indexes, comma-separated (`product_indexes`). JSON columns are text; each database reads
    /// them with its own JSON functions.
    pub fn summary_columns(self) -> &'static str {
        match self {
            Dialect::Sqlite => {
                "id, kind, status, progress, stage, created_us, started_us, finished_us,
                json_extract(result, '$.metrics') IS NOT NULL AS has_metrics,
                (SELECT group_concat(json_extract(value, '$.index')) FROM json_each(result, '$.products'))
                    AS product_indexes"
            }
            Dialect::Postgres => {
                "id, kind, status, progress, stage, created_us, started_us, finished_us,
                COALESCE(jsonb_typeof(result::jsonb -> 'metrics') <> 'null', false) AS has_metrics,
                (SELECT string_agg(p.value ->> 'index', ',' ORDER BY p.n)
                   FROM jsonb_array_elements(result::jsonb -> 'products') WITH ORDINALITY AS p(value, n))
                    AS product_indexes"
            }
        }
    }
}
