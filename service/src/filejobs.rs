//! Map-file I/O off the service's loop: saves and loads asked for over the control
//! channel run on one worker thread, in the order asked, so that writing or reading a
//! map of gigabytes does not stall integration and snapshots for seconds.
//!
//! A save is encoded on the loop (the map must be taken as it is when asked; encoding is
//! parallel and memory-speed) and written here; a load is read and verified here and the
//! loop swaps the map in when it is done.

use std::path::PathBuf;
use std::sync::mpsc::{channel, Receiver, Sender};
use std::thread::JoinHandle;
use voxmap_core::io::mapfile::{self, EncodedMap};
use voxmap_core::OccupancyMap;

pub enum Job {
    Save { path: PathBuf, file: EncodedMap },
    Load { path: PathBuf },
}

/// A finished job, with the path it was for.
pub enum Done {
    Saved(PathBuf, Result<(), String>),
    Loaded(PathBuf, Result<OccupancyMap, String>),
}

pub struct FileWorker {
    jobs: Option<Sender<Job>>,
    done: Receiver<Done>,
    thread: Option<JoinHandle<()>>,
}

impl FileWorker {
    pub fn spawn() -> std::io::Result<Self> {
        let (jobs, rx) = channel::<Job>();
        let (tx, done) = channel();
        let thread = std::thread::Builder::new()
            .name("voxmap-files".into())
            .spawn(move || {
                for job in rx {
                    let d = match job {
                        Job::Save { path, file } => {
                            let r = file.write(&path).map_err(|e| e.to_string());
                            Done::Saved(path, r)
                        }
                        Job::Load { path } => {
                            let r = mapfile::load_map(&path).map_err(|e| e.to_string());
                            Done::Loaded(path, r)
                        }
                    };
                    if tx.send(d).is_err() {
                        break;
                    }
                }
            })?;
        Ok(Self {
            jobs: Some(jobs),
            done,
            thread: Some(thread),
        })
    }

    /// Queue a job; an error if the worker has stopped (it only stops if a job panicked).
    pub fn submit(&self, job: Job) -> Result<(), String> {
        self.jobs
            .as_ref()
            .and_then(|j| j.send(job).ok())
            .ok_or_else(|| "the file worker has stopped".to_string())
    }

    /// The next finished job, if any; jobs finish in the order submitted.
    pub fn try_done(&mut self) -> Option<Done> {
        self.done.try_recv().ok()
    }

    /// Wait for every submitted job and return what is left to hand back, in order.
    pub fn finish(mut self) -> Vec<Done> {
        self.jobs = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        self.done.try_iter().collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use voxmap_core::{SensorModel, VoxelCoord};

    #[test]
    fn jobs_finish_in_order_and_finish_waits_for_all() {
        let dir = std::env::temp_dir().join(format!("voxmap-filejobs-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
        map.set_value(VoxelCoord::new(1, 2, 3), 40);
        let path = dir.join("m.vxm");
        let mut w = FileWorker::spawn().unwrap();
        w.submit(Job::Save {
            path: path.clone(),
            file: mapfile::encode_map_parts(&map),
        })
        .unwrap();
        w.submit(Job::Load { path: path.clone() }).unwrap();
        w.submit(Job::Load {
            path: dir.join("missing.vxm"),
        })
        .unwrap();
        let mut got = Vec::new();
        while got.is_empty() {
            got.extend(w.try_done());
        }
        assert!(matches!(got[0], Done::Saved(..)), "the save finishes first");
        got.extend(w.finish());
        match &got[..] {
            [Done::Saved(_, Ok(())), Done::Loaded(_, Ok(m)), Done::Loaded(p, Err(e))] => {
                assert_eq!(m.grid().get(VoxelCoord::new(1, 2, 3)), Some(40));
                assert!(
                    p.ends_with("missing.vxm") && e.contains("missing.vxm"),
                    "{e}"
                );
            }
            _ => panic!("jobs out of order or failed"),
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
