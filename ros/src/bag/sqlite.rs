//! SQLite storage files (`.db3`): tables `topics(id, name, type, serialization_format, ...)`
//! and `messages(id, topic_id, timestamp, data)`, read in timestamp order.

use super::{BagError, Message, TopicInfo};
use rusqlite::{Connection, OpenFlags};
use std::ops::ControlFlow;
use std::path::Path;

fn open(path: &Path) -> Result<Connection, BagError> {
    let err = |source| BagError::Sqlite {
        path: path.into(),
        source,
    };
    // Read only, and never create: a path that is not a database must fail here.
    let c = Connection::open_with_flags(
        path,
        OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
    )
    .map_err(err)?;
    Ok(c)
}

struct Topic {
    id: i64,
    name: String,
    type_name: String,
    encoding: String,
}

fn topic_rows(c: &Connection) -> rusqlite::Result<Vec<Topic>> {
    let mut s = c.prepare("SELECT id, name, type, serialization_format FROM topics ORDER BY id")?;
    let rows = s.query_map([], |r| {
        Ok(Topic {
            id: r.get(0)?,
            name: r.get(1)?,
            type_name: r.get(2)?,
            encoding: r.get(3)?,
        })
    })?;
    rows.collect()
}

pub(super) fn topics(path: &Path) -> Result<super::Topics, BagError> {
    let c = open(path)?;
    let err = |source| BagError::Sqlite {
        path: path.into(),
        source,
    };
    let rows = topic_rows(&c).map_err(err)?;
    let mut counts = c
        .prepare("SELECT topic_id, COUNT(*), MIN(timestamp), MAX(timestamp) FROM messages GROUP BY topic_id")
        .map_err(err)?;
    let stats: Vec<(i64, i64, i64, i64)> = counts
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)))
        .map_err(err)?
        .collect::<rusqlite::Result<_>>()
        .map_err(err)?;
    let mut span: Option<(u64, u64)> = None;
    for &(_, _, a, b) in &stats {
        let (a, b) = (a.max(0) as u64, b.max(0) as u64);
        span = Some(span.map_or((a, b), |(x, y)| (x.min(a), y.max(b))));
    }
    let topics = rows
        .into_iter()
        .map(|t| TopicInfo {
            count: Some(
                stats
                    .iter()
                    .find(|s| s.0 == t.id)
                    .map_or(0, |s| s.1.max(0) as u64),
            ),
            name: t.name,
            type_name: t.type_name,
            encoding: t.encoding,
        })
        .collect();
    Ok((topics, span))
}

pub(super) fn read(
    path: &Path,
    wanted: &dyn Fn(&str) -> bool,
    f: &mut dyn FnMut(Message<'_>) -> ControlFlow<()>,
) -> Result<(), BagError> {
    let c = open(path)?;
    let err = |source| BagError::Sqlite {
        path: path.into(),
        source,
    };
    let topics: Vec<Topic> = topic_rows(&c)
        .map_err(err)?
        .into_iter()
        .filter(|t| t.encoding == "cdr" && wanted(&t.name))
        .collect();
    if topics.is_empty() {
        return Ok(());
    }
    let ids: Vec<String> = topics.iter().map(|t| t.id.to_string()).collect();
    let sql = format!(
        "SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN ({}) ORDER BY timestamp, id",
        ids.join(",")
    );
    let mut s = c.prepare(&sql).map_err(err)?;
    let mut rows = s.query([]).map_err(err)?;
    while let Some(row) = rows.next().map_err(err)? {
        let id: i64 = row.get(0).map_err(err)?;
        let t: i64 = row.get(1).map_err(err)?;
        let data = row
            .get_ref(2)
            .map_err(err)?
            .as_blob()
            .map_err(|e| err(e.into()))?;
        let Some(topic) = topics.iter().find(|x| x.id == id) else {
            continue;
        };
        let m = Message {
            topic: &topic.name,
            type_name: &topic.type_name,
            log_time_ns: t.max(0) as u64,
            data,
        };
        if f(m).is_break() {
            break;
        }
    }
    Ok(())
}
