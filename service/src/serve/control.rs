//! Control requests (stats, save, load, clear, scope), answered between frames.
//!
//! Saves and loads run on the file worker ([`crate::filejobs`]); while one runs, requests
//! other than stats wait behind it in order ([`Control::deferred`]), so that they see the
//! map as the file job leaves it and one save at a time holds a copy. A finished file job
//! is answered first (a loaded map swapped in), then the requests deferred behind it, then
//! new ones.

use super::MapState;
use crate::filejobs::{Done, FileWorker, Job};
use anyhow::{anyhow, Result};
use iceoryx2::active_request::ActiveRequest;
use iceoryx2::port::server::Server;
use iceoryx2::prelude::*;
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use voxmap_ipc::{ControlKind, ControlRequest, ControlResponse};
use voxmap_map::mapper::StoreConfig;

type Request = ActiveRequest<ipc::Service, ControlRequest, (), ControlResponse, ()>;

/// An answer: success, message, and whether the map changed so that a snapshot is due.
struct Answer {
    ok: bool,
    message: String,
    republish: bool,
}

impl Answer {
    fn ok(message: String, republish: bool) -> Self {
        Self {
            ok: true,
            message,
            republish,
        }
    }

    fn err(message: String) -> Self {
        Self {
            ok: false,
            message,
            republish: false,
        }
    }
}

/// The control server with its queues of requests in flight.
pub(super) struct Control {
    server: Server<ipc::Service, ControlRequest, (), ControlResponse, ()>,
    files: FileWorker,
    /// Requests whose file job is running, in the order of the jobs.
    waiting: VecDeque<Request>,
    /// Requests that came while a file job ran, in order.
    deferred: VecDeque<Request>,
}

impl Control {
    pub fn new(
        server: Server<ipc::Service, ControlRequest, (), ControlResponse, ()>,
    ) -> Result<Self> {
        Ok(Self {
            server,
            files: FileWorker::spawn()
                .map_err(|e| anyhow!(e).context("starting the file worker"))?,
            waiting: VecDeque::new(),
            deferred: VecDeque::new(),
        })
    }

    /// Answer every request that can be answered now; `publish` is called when a request
    /// changed the map or its scope, before the answer goes out.
    pub fn serve(
        &mut self,
        s: &mut MapState,
        mut publish: impl FnMut(&mut MapState),
    ) -> Result<()> {
        loop {
            let (req, answer) = if let Some(done) = self.files.try_done() {
                let req = self
                    .waiting
                    .pop_front()
                    .expect("one waiting request per file job");
                (req, finish_file_job(done, s))
            } else {
                let next = match self.waiting.is_empty() {
                    true => self.deferred.pop_front(),
                    false => None,
                };
                let req = match next {
                    Some(req) => req,
                    None => match self
                        .server
                        .receive()
                        .map_err(|e| anyhow!(e).context("receiving a control request"))?
                    {
                        Some(req) => req,
                        None => return Ok(()),
                    },
                };
                let r = *req.payload();
                if !self.waiting.is_empty() && r.kind().ok() != Some(ControlKind::Stats) {
                    self.deferred.push_back(req);
                    continue;
                }
                match self.answer(&r, s) {
                    Some(a) => (req, a),
                    // A file job took it; it is answered when the job is done.
                    None => {
                        self.waiting.push_back(req);
                        continue;
                    }
                }
            };
            if !answer.ok {
                eprintln!("voxmap serve: control request failed: {}", answer.message);
            }
            if answer.republish {
                publish(s);
            }
            if let Err(e) = req.send_copy(ControlResponse::new(
                answer.ok,
                &answer.message,
                s.stats.wire(&s.mapper),
            )) {
                // The client may have gone; anything else is worth a line.
                eprintln!("voxmap serve: control response not sent: {e:?}");
            }
        }
    }

    /// The answer to `r`, or `None` when a file job was started for it.
    fn answer(&mut self, r: &ControlRequest, s: &mut MapState) -> Option<Answer> {
        let kind = match r.kind() {
            Ok(k) => k,
            Err(e) => return Some(Answer::err(e.to_string())),
        };
        Some(match kind {
            ControlKind::Stats => Answer::ok(String::new(), false),
            ControlKind::Save | ControlKind::Load => {
                let Some(p) = r.path() else {
                    return Some(Answer::err("bad path".into()));
                };
                let path: PathBuf = p.into();
                if kind == ControlKind::Load && voxmap_map::store::exists(&path) {
                    return Some(load_store(&path, s));
                }
                if let Some(dir) = s.mapper.store_dir().map(Path::to_path_buf) {
                    return Some(store_file_request(kind, &path, &dir, s));
                }
                let job = if kind == ControlKind::Save {
                    let file = s.mapper.encode_file();
                    Job::Save { path, file }
                } else {
                    Job::Load { path }
                };
                match self.files.submit(job) {
                    Ok(()) => return None,
                    Err(e) => Answer::err(e),
                }
            }
            ControlKind::Clear => {
                s.mapper.clear();
                Answer::ok("cleared".into(), true)
            }
            ControlKind::SetScope => match r.scope() {
                Ok(scope) => {
                    s.scope = scope;
                    Answer::ok(format!("scope {scope:?}"), true)
                }
                Err(e) => Answer::err(e.to_string()),
            },
        })
    }

    /// At exit: a save being written is finished and answered; a load is not waited for
    /// (nor swapped in if it is done), and requests still deferred are refused.
    pub fn finish(self, s: &mut MapState) {
        let mut finished = self.files.finish().into_iter();
        for req in self.waiting.into_iter().chain(self.deferred) {
            let answer = match finished.next() {
                Some(Done::Loaded(_, Ok(_))) | None => {
                    Answer::err("not done: the service is exiting".into())
                }
                Some(done) => finish_file_job(done, s),
            };
            if let Err(e) = req.send_copy(ControlResponse::new(
                answer.ok,
                &answer.message,
                s.stats.wire(&s.mapper),
            )) {
                // The client may have gone; anything else is worth a line.
                eprintln!("voxmap serve: control response not sent: {e:?}");
            }
        }
    }
}

/// `load` of a tile store's directory: the service continues that store, lazily (its
/// tiles load as frames and snapshot windows reach them), in place of its map, keeping its
/// memory budget. The map it had, and its own store's changes since their last save, are
/// dropped, as a loaded map file drops them. Runs in the loop: opening reads the manifest.
fn load_store(dir: &Path, s: &mut MapState) -> Answer {
    let cfg = StoreConfig {
        dir: dir.into(),
        memory_budget: s.mapper.tile_stats().and_then(|t| t.memory_budget),
        resume: true,
    };
    match s.mapper.switch_store(&cfg) {
        Ok(()) => {
            let stored = s.mapper.tile_stats().map_or(0, |t| t.tiles_stored);
            Answer::ok(
                format!(
                    "continuing the tile store {} ({stored} tiles stored, last frame {})",
                    dir.display(),
                    s.mapper.last_frame().sequence
                ),
                true,
            )
        }
        Err(e) => Answer::err(format!("{} not loaded: {e}", dir.display())),
    }
}

/// `save` and `load` of a map file when the map is kept in a tile store. `save` to the
/// store's directory saves incrementally (the tiles changed since the last save, then the
/// manifest); to another path it writes a map file of every tile, streamed. Both run in
/// the loop: frames wait meanwhile. A map file's `load` is refused: the store is the map.
fn store_file_request(kind: ControlKind, path: &Path, dir: &Path, s: &mut MapState) -> Answer {
    if kind == ControlKind::Load {
        return Answer::err(format!(
            "{} not loaded: the map is kept in the tile store {}; a map file does not load into a store (load a store's directory, or restart without --store)",
            path.display(),
            dir.display()
        ));
    }
    let same = |a: &Path, b: &Path| match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => a == b,
    };
    if same(path, dir) {
        return match s.mapper.save_store() {
            Some(Ok(r)) => Answer::ok(
                format!(
                    "saved to the tile store {}: {} tiles written, generation {}, {:.1} ms",
                    dir.display(),
                    r.tiles_written,
                    r.generation,
                    r.time.as_secs_f64() * 1e3
                ),
                false,
            ),
            Some(Err(e)) => Answer::err(format!("saving the tile store: {e}")),
            None => Answer::err("no tile store".into()),
        };
    }
    match s.mapper.write_map_file(path) {
        Ok(leaves) => Answer::ok(
            format!("saved to {} ({leaves} leaves)", path.display()),
            false,
        ),
        Err(e) => Answer::err(format!("saving to {}: {e}", path.display())),
    }
}

/// Apply a finished file job: a loaded map replaces the map unless the integrator cannot
/// work at its resolution.
fn finish_file_job(done: Done, s: &mut MapState) -> Answer {
    match done {
        Done::Saved(p, Ok(())) => Answer::ok(format!("saved to {}", p.display()), false),
        Done::Loaded(p, Ok(loaded)) => {
            let (m, carried) = *loaded;
            match s.load(m, carried) {
                Ok(()) => Answer::ok(format!("loaded {}", p.display()), true),
                Err(e) => Answer::err(format!("{} not loaded: {e}", p.display())),
            }
        }
        Done::Saved(_, Err(e)) | Done::Loaded(_, Err(e)) => Answer::err(e),
    }
}
