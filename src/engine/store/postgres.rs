//! The PostgreSQL store: one table shared by every replica, so replicas hold no state of their
//! own and a plant's existing database is the system of record.
//!
//! A write is one transaction: an advisory lock on the ID (two replicas registering one ID at
//! once are serialised), the check against the existing row, the insert or update, and a
//! `NOTIFY` on [`CHANNEL`] that PostgreSQL delivers to every listener when (and only if) the
//! transaction commits. Each replica keeps one extra connection that `LISTEN`s and turns the
//! notifications into [`StoreEvent`]s for its template cache; when that connection is lost it
//! reconnects with backoff, listens again and announces [`StoreEvent::Resynchronise`], because
//! anything may have changed meanwhile. Requests use a small pool of other connections.
//!
//! The schema is created and migrated at start by [`MIGRATIONS`], applied in order under an
//! advisory lock (replicas starting together migrate once) and recorded in
//! `posematch_schema_migrations`. Connections are plaintext (`NoTls`): keep the database on the
//! cluster's private network.

use std::collections::BTreeMap;
use std::sync::Mutex;
use std::time::Duration;

use deadpool_postgres::{ManagerConfig, Pool, PoolError, RecyclingMethod, Runtime};
use serde::{Deserialize, Serialize};
use tokio::sync::mpsc;
use tokio_postgres::error::SqlState;
use tokio_postgres::types::Json;
use tokio_postgres::{AsyncMessage, NoTls, Row};

use super::{
    CalibrationRecord, NewTemplate, Opened, PutOutcome, StoreError, StoreEvent, TemplateMeta,
};
use crate::engine::Metrics;
use crate::geometry::TemplateOrigin;
use crate::world::CalibrationSpec;

/// The `LISTEN`/`NOTIFY` channel of template changes.
pub const CHANNEL: &str = "posematch_templates";

/// Versioned schema changes, applied once each, in order. Never edit one that has shipped:
/// add the next version.
const MIGRATIONS: &[(i32, &str, &str)] = &[
    (
        1,
        "templates table",
        r#"CREATE TABLE posematch_templates (
        template_id    text COLLATE "C" PRIMARY KEY,
        image_png      bytea NOT NULL,
        content_sha256 text NOT NULL CHECK (content_sha256 ~ '^[0-9a-f]{64}$'),
        width          integer NOT NULL CHECK (width > 0),
        height         integer NOT NULL CHECK (height > 0),
        labels         jsonb NOT NULL DEFAULT '{}'::jsonb,
        created_at     timestamptz NOT NULL,
        updated_at     timestamptz NOT NULL,
        version        bigint NOT NULL CHECK (version > 0)
    )"#,
    ),
    (
        2,
        "template origins",
        r#"ALTER TABLE posematch_templates
        ADD COLUMN origin_x real,
        ADD COLUMN origin_y real,
        ADD CONSTRAINT posematch_templates_origin_both CHECK ((origin_x IS NULL) = (origin_y IS NULL))"#,
    ),
    (
        3,
        "calibrations table",
        r#"CREATE TABLE posematch_calibrations (
        calibration_id text COLLATE "C" PRIMARY KEY,
        spec           jsonb NOT NULL,
        created_at     timestamptz NOT NULL,
        updated_at     timestamptz NOT NULL,
        version        bigint NOT NULL CHECK (version > 0)
    )"#,
    ),
];

/// The calibration columns, as [`calibration_of`] reads them.
const CALIBRATION_COLUMNS: &str = "calibration_id, spec, \
    (extract(epoch from created_at) * 1000)::bigint AS created_unix_ms, \
    (extract(epoch from updated_at) * 1000)::bigint AS updated_unix_ms, version";

/// Advisory lock key held while migrating (any constant; "pmatch" in ASCII).
const MIGRATION_LOCK: i64 = 0x706d_6174_6368;

/// Longest a request waits for a pooled connection, and for any one store operation.
const CONNECTION_WAIT: Duration = Duration::from_secs(5);
const OPERATION_TIMEOUT: Duration = Duration::from_secs(10);
/// Connections a replica keeps for requests (the listener has its own).
const POOL_SIZE: usize = 4;
/// Reconnection backoff of the listener.
const RECONNECT_FIRST: Duration = Duration::from_millis(200);
const RECONNECT_MOST: Duration = Duration::from_secs(5);

/// The metadata columns, as [`meta_of`] reads them.
const META_COLUMNS: &str = "template_id, width, height, labels, content_sha256, \
    (extract(epoch from created_at) * 1000)::bigint AS created_unix_ms, \
    (extract(epoch from updated_at) * 1000)::bigint AS updated_unix_ms, version, \
    origin_x, origin_y";

/// A `postgres://` URL, parsed; shown without its password.
#[derive(Clone)]
pub struct PostgresUrl {
    config: tokio_postgres::Config,
}

impl PostgresUrl {
    pub fn parse(url: &str) -> Result<Self, String> {
        let mut config: tokio_postgres::Config = url.parse().map_err(|e| {
            format!(
                "not a PostgreSQL URL ({e}); use postgres://USER[:PASSWORD]@HOST[:PORT]/DATABASE"
            )
        })?;
        if config.get_hosts().is_empty() {
            return Err(
                "the PostgreSQL URL names no host; use postgres://USER@HOST/DATABASE".into(),
            );
        }
        if config.get_connect_timeout().is_none() {
            config.connect_timeout(CONNECTION_WAIT);
        }
        if config.get_application_name().is_none() {
            config.application_name("posematch");
        }
        // A dead peer (no RST: a cut cable, a vanished node) is noticed within a minute.
        config.keepalives_idle(Duration::from_secs(30));
        Ok(Self { config })
    }
}

impl std::fmt::Display for PostgresUrl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let c = &self.config;
        write!(f, "postgres://")?;
        if let Some(user) = c.get_user() {
            write!(f, "{user}@")?;
        }
        for (i, host) in c.get_hosts().iter().enumerate() {
            if i > 0 {
                write!(f, ",")?;
            }
            match host {
                tokio_postgres::config::Host::Tcp(name) => write!(f, "{name}")?,
                #[cfg(unix)]
                tokio_postgres::config::Host::Unix(path) => write!(f, "{}", path.display())?,
            }
            if let Some(port) = c.get_ports().get(i).or(c.get_ports().first()) {
                write!(f, ":{port}")?;
            }
        }
        write!(f, "/{}", c.get_dbname().unwrap_or(""))
    }
}

impl std::fmt::Debug for PostgresUrl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PostgresUrl({self})")
    }
}

/// What a notification carries: the ID, its new content (`None`: deleted), and whether the ID
/// is new.
#[derive(Debug, Serialize, Deserialize)]
struct Announcement {
    template_id: String,
    content_sha256: Option<String>,
    #[serde(default)]
    created: bool,
}

pub struct PostgresStore {
    pool: Pool,
    events: Mutex<Option<mpsc::UnboundedReceiver<StoreEvent>>>,
    listener: tokio::task::JoinHandle<()>,
}

impl Drop for PostgresStore {
    fn drop(&mut self) {
        self.listener.abort();
    }
}

impl PostgresStore {
    /// Connects, migrates the schema and starts listening; fails if the database cannot be
    /// reached now.
    pub async fn open(url: &PostgresUrl, metrics: Metrics) -> Result<(Self, Opened), StoreError> {
        let manager = deadpool_postgres::Manager::from_config(
            url.config.clone(),
            NoTls,
            ManagerConfig {
                // A test query on every checkout: after a database restart no request gets a
                // connection that died with it.
                recycling_method: RecyclingMethod::Verified,
            },
        );
        let pool = Pool::builder(manager)
            .max_size(POOL_SIZE)
            .wait_timeout(Some(CONNECTION_WAIT))
            .create_timeout(Some(CONNECTION_WAIT))
            .recycle_timeout(Some(CONNECTION_WAIT))
            .runtime(Runtime::Tokio1)
            .build()
            .map_err(|e| StoreError::Database(format!("connection pool: {e}")))?;
        migrate(&pool).await?;
        // Listening before the first template is read: no change can slip between the two.
        let (sender, events) = mpsc::unbounded_channel();
        let first = listen(&url.config).await?;
        let listener = tokio::spawn(keep_listening(url.config.clone(), first, sender, metrics));
        let store = Self {
            pool,
            events: Mutex::new(Some(events)),
            listener,
        };
        let templates = store.count().await?;
        Ok((
            store,
            Opened {
                templates,
                set_aside: 0,
            },
        ))
    }

    pub fn take_events(&self) -> Option<mpsc::UnboundedReceiver<StoreEvent>> {
        self.events.lock().expect("events lock").take()
    }

    pub async fn count(&self) -> Result<usize, StoreError> {
        within_timeout(async {
            let client = self.pool.get().await.map_err(pool_error)?;
            let row = client
                .query_one("SELECT count(*) FROM posematch_templates", &[])
                .await
                .map_err(db_error)?;
            Ok(row.get::<_, i64>(0) as usize)
        })
        .await
    }

    pub async fn get(&self, template_id: &str) -> Result<Option<TemplateMeta>, StoreError> {
        within_timeout(async {
            let client = self.pool.get().await.map_err(pool_error)?;
            let sql =
                format!("SELECT {META_COLUMNS} FROM posematch_templates WHERE template_id = $1");
            let row = client
                .query_opt(&sql, &[&template_id])
                .await
                .map_err(db_error)?;
            Ok(row.map(|r| meta_of(&r)))
        })
        .await
    }

    pub async fn get_with_image(
        &self,
        template_id: &str,
    ) -> Result<Option<(TemplateMeta, Vec<u8>)>, StoreError> {
        within_timeout(async {
            let client = self.pool.get().await.map_err(pool_error)?;
            let sql = format!(
                "SELECT {META_COLUMNS}, image_png FROM posematch_templates WHERE template_id = $1"
            );
            let row = client
                .query_opt(&sql, &[&template_id])
                .await
                .map_err(db_error)?;
            Ok(row.map(|r| (meta_of(&r), r.get::<_, Vec<u8>>("image_png"))))
        })
        .await
    }

    pub async fn list(
        &self,
        after: Option<&str>,
        limit: usize,
    ) -> Result<Vec<TemplateMeta>, StoreError> {
        within_timeout(async {
            let client = self.pool.get().await.map_err(pool_error)?;
            let sql = format!(
                "SELECT {META_COLUMNS} FROM posematch_templates \
                 WHERE $1::text IS NULL OR template_id > $1 ORDER BY template_id LIMIT $2"
            );
            let rows = client
                .query(&sql, &[&after, &(limit as i64)])
                .await
                .map_err(db_error)?;
            Ok(rows.iter().map(meta_of).collect())
        })
        .await
    }

    pub async fn put(&self, new: &NewTemplate, replace: bool) -> Result<PutOutcome, StoreError> {
        within_timeout(async {
            let mut client = self.pool.get().await.map_err(pool_error)?;
            let tx = client.transaction().await.map_err(db_error)?;
            lock_id(&tx, &new.template_id).await?;
            let sql =
                format!("SELECT {META_COLUMNS} FROM posematch_templates WHERE template_id = $1");
            let existing = tx
                .query_opt(&sql, &[&new.template_id])
                .await
                .map_err(db_error)?
                .map(|r| meta_of(&r));
            if let Some(existing) = existing.as_ref() {
                if existing.content_sha256 == new.content_sha256 {
                    return Ok(PutOutcome::Unchanged(existing.clone()));
                }
                if !replace {
                    return Ok(PutOutcome::Conflict(existing.clone()));
                }
            }
            let (width, height) = (new.width as i32, new.height as i32);
            let labels = Json(&new.labels);
            let sql = if existing.is_some() {
                format!(
                    "UPDATE posematch_templates SET image_png = $2, content_sha256 = $3, \
                     width = $4, height = $5, labels = $6, origin_x = $7, origin_y = $8, \
                     updated_at = now(), version = version + 1 WHERE template_id = $1 \
                     RETURNING {META_COLUMNS}"
                )
            } else {
                format!(
                    "INSERT INTO posematch_templates (template_id, image_png, content_sha256, \
                     width, height, labels, origin_x, origin_y, created_at, updated_at, version) \
                     VALUES ($1, $2, $3, $4, $5, $6, $7, $8, now(), now(), 1) \
                     RETURNING {META_COLUMNS}"
                )
            };
            let (origin_x, origin_y) = (new.origin.map(|o| o.x), new.origin.map(|o| o.y));
            let params: [&(dyn tokio_postgres::types::ToSql + Sync); 8] = [
                &new.template_id,
                &new.png,
                &new.content_sha256,
                &width,
                &height,
                &labels,
                &origin_x,
                &origin_y,
            ];
            let row = tx.query_one(&sql, &params).await.map_err(db_error)?;
            let meta = meta_of(&row);
            let created = existing.is_none();
            announce(&tx, &meta.template_id, Some(&meta.content_sha256), created).await?;
            tx.commit().await.map_err(db_error)?;
            Ok(PutOutcome::Written { meta, created })
        })
        .await
    }

    pub async fn remove(&self, template_id: &str) -> Result<bool, StoreError> {
        within_timeout(async {
            let mut client = self.pool.get().await.map_err(pool_error)?;
            let tx = client.transaction().await.map_err(db_error)?;
            lock_id(&tx, template_id).await?;
            let removed = tx
                .execute(
                    "DELETE FROM posematch_templates WHERE template_id = $1",
                    &[&template_id],
                )
                .await
                .map_err(db_error)?;
            if removed == 0 {
                return Ok(false);
            }
            announce(&tx, template_id, None, false).await?;
            tx.commit().await.map_err(db_error)?;
            Ok(true)
        })
        .await
    }
}

impl PostgresStore {
    pub async fn get_calibration(
        &self,
        calibration_id: &str,
    ) -> Result<Option<CalibrationRecord>, StoreError> {
        within_timeout(async {
            let client = self.pool.get().await.map_err(pool_error)?;
            let sql = format!(
                "SELECT {CALIBRATION_COLUMNS} FROM posematch_calibrations WHERE calibration_id = $1"
            );
            let row = client
                .query_opt(&sql, &[&calibration_id])
                .await
                .map_err(db_error)?;
            row.map(|r| calibration_of(&r)).transpose()
        })
        .await
    }

    pub async fn list_calibrations(
        &self,
        after: Option<&str>,
        limit: usize,
    ) -> Result<Vec<CalibrationRecord>, StoreError> {
        within_timeout(async {
            let client = self.pool.get().await.map_err(pool_error)?;
            let sql = format!(
                "SELECT {CALIBRATION_COLUMNS} FROM posematch_calibrations \
                 WHERE $1::text IS NULL OR calibration_id > $1 ORDER BY calibration_id LIMIT $2"
            );
            let rows = client
                .query(&sql, &[&after, &(limit as i64)])
                .await
                .map_err(db_error)?;
            rows.iter().map(calibration_of).collect()
        })
        .await
    }

    pub async fn put_calibration(
        &self,
        calibration_id: &str,
        spec: &CalibrationSpec,
        replace: bool,
    ) -> Result<PutOutcome<CalibrationRecord>, StoreError> {
        within_timeout(async {
            let mut client = self.pool.get().await.map_err(pool_error)?;
            let tx = client.transaction().await.map_err(db_error)?;
            lock_id(&tx, &format!("calibration:{calibration_id}")).await?;
            let sql = format!(
                "SELECT {CALIBRATION_COLUMNS} FROM posematch_calibrations WHERE calibration_id = $1"
            );
            let existing = tx
                .query_opt(&sql, &[&calibration_id])
                .await
                .map_err(db_error)?
                .map(|r| calibration_of(&r))
                .transpose()?;
            if let Some(existing) = existing.as_ref() {
                if &existing.spec == spec {
                    return Ok(PutOutcome::Unchanged(existing.clone()));
                }
                if !replace {
                    return Ok(PutOutcome::Conflict(existing.clone()));
                }
            }
            let json = Json(spec);
            let sql = if existing.is_some() {
                format!(
                    "UPDATE posematch_calibrations SET spec = $2, updated_at = now(), \
                     version = version + 1 WHERE calibration_id = $1 RETURNING {CALIBRATION_COLUMNS}"
                )
            } else {
                format!(
                    "INSERT INTO posematch_calibrations (calibration_id, spec, created_at, \
                     updated_at, version) VALUES ($1, $2, now(), now(), 1) \
                     RETURNING {CALIBRATION_COLUMNS}"
                )
            };
            let row = tx
                .query_one(&sql, &[&calibration_id, &json])
                .await
                .map_err(db_error)?;
            let record = calibration_of(&row)?;
            tx.commit().await.map_err(db_error)?;
            Ok(PutOutcome::Written {
                meta: record,
                created: existing.is_none(),
            })
        })
        .await
    }

    pub async fn remove_calibration(&self, calibration_id: &str) -> Result<bool, StoreError> {
        within_timeout(async {
            let client = self.pool.get().await.map_err(pool_error)?;
            let removed = client
                .execute(
                    "DELETE FROM posematch_calibrations WHERE calibration_id = $1",
                    &[&calibration_id],
                )
                .await
                .map_err(db_error)?;
            Ok(removed > 0)
        })
        .await
    }
}

fn calibration_of(row: &Row) -> Result<CalibrationRecord, StoreError> {
    let calibration_id: String = row.get("calibration_id");
    let spec: Json<CalibrationSpec> = row.try_get("spec").map_err(|e| StoreError::Corrupt {
        origin: format!("calibration `{}`", calibration_id.escape_debug()),
        message: e.to_string(),
    })?;
    Ok(CalibrationRecord {
        calibration_id,
        spec: spec.0,
        created_unix_ms: row.get("created_unix_ms"),
        updated_unix_ms: row.get("updated_unix_ms"),
        version: row.get("version"),
    })
}

/// Serialises writers of one ID across replicas until the transaction ends.
async fn lock_id(
    tx: &deadpool_postgres::Transaction<'_>,
    template_id: &str,
) -> Result<(), StoreError> {
    tx.execute(
        "SELECT pg_advisory_xact_lock(hashtextextended($1, 0))",
        &[&template_id],
    )
    .await
    .map_err(db_error)?;
    Ok(())
}

/// Queues the change notification; PostgreSQL delivers it when the transaction commits.
async fn announce(
    tx: &deadpool_postgres::Transaction<'_>,
    template_id: &str,
    content_sha256: Option<&str>,
    created: bool,
) -> Result<(), StoreError> {
    let payload = serde_json::to_string(&Announcement {
        template_id: template_id.to_owned(),
        content_sha256: content_sha256.map(str::to_owned),
        created,
    })
    .expect("announcement serialises");
    tx.execute("SELECT pg_notify($1, $2)", &[&CHANNEL, &payload])
        .await
        .map_err(db_error)?;
    Ok(())
}

fn meta_of(row: &Row) -> TemplateMeta {
    let labels: Json<BTreeMap<String, String>> = row.get("labels");
    TemplateMeta {
        template_id: row.get("template_id"),
        width: row.get::<_, i32>("width") as u32,
        height: row.get::<_, i32>("height") as u32,
        labels: labels.0,
        content_sha256: row.get("content_sha256"),
        created_unix_ms: row.get("created_unix_ms"),
        updated_unix_ms: row.get("updated_unix_ms"),
        version: row.get("version"),
        origin: match (row.get("origin_x"), row.get("origin_y")) {
            (Some(x), Some(y)) => Some(TemplateOrigin { x, y }),
            _ => None,
        },
    }
}

async fn migrate(pool: &Pool) -> Result<(), StoreError> {
    within_timeout(async {
        let mut client = pool.get().await.map_err(pool_error)?;
        let tx = client.transaction().await.map_err(db_error)?;
        tx.execute("SELECT pg_advisory_xact_lock($1)", &[&MIGRATION_LOCK])
            .await
            .map_err(db_error)?;
        tx.batch_execute(
            "CREATE TABLE IF NOT EXISTS posematch_schema_migrations (
                version     integer PRIMARY KEY,
                description text NOT NULL,
                applied_at  timestamptz NOT NULL DEFAULT now()
            )",
        )
        .await
        .map_err(db_error)?;
        let applied: Vec<i32> = tx
            .query("SELECT version FROM posematch_schema_migrations", &[])
            .await
            .map_err(db_error)?
            .iter()
            .map(|r| r.get(0))
            .collect();
        for (version, description, sql) in MIGRATIONS {
            if applied.contains(version) {
                continue;
            }
            tx.batch_execute(sql).await.map_err(|e| {
                StoreError::Database(format!("schema migration {version} ({description}): {e}"))
            })?;
            tx.execute(
                "INSERT INTO posematch_schema_migrations (version, description) VALUES ($1, $2)",
                &[version, description],
            )
            .await
            .map_err(db_error)?;
            tracing::info!(version, description, "template database schema migrated");
        }
        let newest = MIGRATIONS.last().map_or(0, |m| m.0);
        if let Some(newer) = applied.iter().filter(|v| **v > newest).max() {
            tracing::warn!(
                database = newer,
                ours = newest,
                "the template database has a newer schema than this build knows; running on it (migrations only add)"
            );
        }
        tx.commit().await.map_err(db_error)?;
        Ok(())
    })
    .await
}

/// A connection that listens on [`CHANNEL`]: its notifications, and a task driving it that
/// ends when the connection does.
struct Listening {
    notifications: mpsc::UnboundedReceiver<tokio_postgres::Notification>,
    _client: tokio_postgres::Client,
}

async fn listen(config: &tokio_postgres::Config) -> Result<Listening, StoreError> {
    within_timeout(async {
        let (client, mut connection) = config.connect(NoTls).await.map_err(db_error)?;
        let (sender, notifications) = mpsc::unbounded_channel();
        tokio::spawn(async move {
            let mut messages = futures_util::stream::poll_fn(move |cx| connection.poll_message(cx));
            while let Some(message) = futures_util::StreamExt::next(&mut messages).await {
                match message {
                    Ok(AsyncMessage::Notification(n)) => {
                        if sender.send(n).is_err() {
                            return;
                        }
                    }
                    Ok(_) => {}
                    Err(e) => {
                        tracing::warn!(error = %e, "template database notification connection lost");
                        return;
                    }
                }
            }
        });
        client
            .batch_execute(&format!("LISTEN {CHANNEL}"))
            .await
            .map_err(db_error)?;
        Ok(Listening {
            notifications,
            _client: client,
        })
    })
    .await
}

/// Forwards notifications as [`StoreEvent`]s for as long as the store lives, reconnecting
/// whenever the listening connection is lost.
async fn keep_listening(
    config: tokio_postgres::Config,
    first: Listening,
    events: mpsc::UnboundedSender<StoreEvent>,
    metrics: Metrics,
) {
    let mut listening = first;
    loop {
        while let Some(notification) = listening.notifications.recv().await {
            metrics.store_notifications.inc();
            let event = match serde_json::from_str::<Announcement>(notification.payload()) {
                Ok(a) => StoreEvent::Changed {
                    template_id: a.template_id,
                    content_sha256: a.content_sha256,
                    created: a.created,
                },
                // Not ours to read (another version's format?): trust nothing cached.
                Err(_) => StoreEvent::Resynchronise,
            };
            if events.send(event).is_err() {
                return;
            }
        }
        metrics.store_listening.set(0);
        let mut wait = RECONNECT_FIRST;
        listening = loop {
            tokio::time::sleep(wait).await;
            match listen(&config).await {
                Ok(listening) => break listening,
                Err(e) => {
                    tracing::debug!(error = %e, "template database still unreachable");
                    wait = (wait * 2).min(RECONNECT_MOST);
                }
            }
        };
        metrics.store_listening.set(1);
        metrics.store_reconnects.inc();
        tracing::info!(
            "template database reachable again; listening for changes, cached templates dropped"
        );
        if events.send(StoreEvent::Resynchronise).is_err() {
            return;
        }
    }
}

async fn within_timeout<T>(
    work: impl Future<Output = Result<T, StoreError>>,
) -> Result<T, StoreError> {
    tokio::time::timeout(OPERATION_TIMEOUT, work)
        .await
        .unwrap_or_else(|_| {
            Err(StoreError::Unavailable(format!(
                "no answer within {} s",
                OPERATION_TIMEOUT.as_secs()
            )))
        })
}

fn pool_error(e: PoolError) -> StoreError {
    match e {
        PoolError::Backend(e) => db_error(e),
        PoolError::Timeout(_) => StoreError::Unavailable(format!(
            "no connection within {} s",
            CONNECTION_WAIT.as_secs()
        )),
        other => StoreError::Database(other.to_string()),
    }
}

/// Connection trouble (worth retrying) is [`StoreError::Unavailable`]; anything the database
/// itself refused is [`StoreError::Database`].
fn db_error(e: tokio_postgres::Error) -> StoreError {
    if e.code() == Some(&SqlState::DISK_FULL) {
        tracing::warn!(error = %e, "the template database's disk is full");
        return StoreError::Full("the template database has no space left".into());
    }
    let transient = match e.code() {
        None => true,
        Some(code) => {
            code.code().starts_with("08")
                || [
                    SqlState::ADMIN_SHUTDOWN,
                    SqlState::CRASH_SHUTDOWN,
                    SqlState::CANNOT_CONNECT_NOW,
                    SqlState::TOO_MANY_CONNECTIONS,
                ]
                .contains(code)
        }
    };
    let message = match (e.as_db_error(), std::error::Error::source(&e)) {
        (Some(db), _) => db.message().to_owned(),
        // "error connecting to server: Connection refused (os error 111)", not only the first half.
        (None, Some(cause)) => format!("{e}: {cause}"),
        (None, None) => e.to_string(),
    };
    if transient {
        StoreError::Unavailable(message)
    } else {
        StoreError::Database(message)
    }
}
