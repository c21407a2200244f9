//! Map-file I/O off the service's loop: saves and loads asked for over the control
//! channel run on one worker thread, in the order asked, so that writing or reading a
//! map of gigabytes does not stall integration and snapshots for seconds.
//!
//! A save is encoded on the loop (the map must be taken as it is when asked; encoding is
//! parallel and memory-speed) and written here; a load is read and verified here and the
//! loop swaps the map in when it is done.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::mpsc::{channel, Receiver, Sender};
use voxmap_map::field::DistanceField;
use voxmap_map::io::mapfile::{self, EncodedMap};
use voxmap_map::OccupancyMap;

pub enum Job {
    Save { path: PathBuf, file: EncodedMap },
    Load { path: PathBuf },
}

/// A finished job, with the path it was for.
pub enum Done {
    Saved(PathBuf, Result<(), String>),
    /// The map, and the distance field the file carried.
    Loaded(PathBuf, Result<Box<Loaded>, String>),
}

/// A map read from a file, and the distance field the file carried.
pub type Loaded = (OccupancyMap, Option<DistanceField>);

pub struct FileWorker {
    jobs: Sender<Job>,
    done: Receiver<Done>,
    /// Per job submitted and not yet handed back, in order: whether it is a save.
    saves: VecDeque<bool>,
}

impl FileWorker {
    pub fn spawn() -> std::io::Result<Self> {
        let (jobs, rx) = channel::<Job>();
        let (tx, done) = channel();
        // Detached: at exit the service waits for saves only (see `finish`).
        std::thread::Builder::new()
            .name("voxmap-files".into())
            .spawn(move || {
                for job in rx {
                    let d = match job {
                        Job::Save { path, file } => {
                            let r = file.write(&path).map_err(|e| e.to_string());
                            Done::Saved(path, r)
                        }
                        Job::Load { path } => {
                            let r = mapfile::load_map_with_field(&path)
                                .map(Box::new)
                                .map_err(|e| e.to_string());
                            Done::Loaded(path, r)
                        }
                    };
                    if tx.send(d).is_err() {
                        break;
                    }
                }
            })?;
        Ok(Self {
            jobs,
            done,
            saves: VecDeque::new(),
        })
    }

    /// Queue a job; an error if the worker has stopped (it only stops if a job panicked).
    pub fn submit(&mut self, job: Job) -> Result<(), String> {
        let save = matches!(job, Job::Save { .. });
        self.jobs
            .send(job)
            .map_err(|_| "the file worker has stopped".to_string())?;
        self.saves.push_back(save);
        Ok(())
    }

    /// The next finished job, if any; jobs finish in the order submitted.
    pub fn try_done(&mut self) -> Option<Done> {
        let d = self.done.try_recv().ok()?;
        self.saves.pop_front();
        Some(d)
    }

    /// For shutdown: wait for the saves at the front of the queue, and return the jobs
    /// finished by then, in order. A load is not waited for (one stuck on a dead file
    /// system must not hold up the exit), nor anything queued behind it.
    pub fn finish(mut self) -> Vec<Done> {
        let mut out: Vec<Done> = self.done.try_iter().collect();
        for _ in &out {
            self.saves.pop_front();
        }
        while self.saves.front() == Some(&true) {
            match self.done.recv() {
                Ok(d) => {
                    self.saves.pop_front();
                    out.push(d);
                }
                Err(_) => break,
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use voxmap_map::{SensorModel, VoxelCoord};

    #[test]
    fn jobs_finish_in_order_and_the_exit_waits_for_saves_only() {
        let dir = std::env::temp_dir().join(format!("voxmap-filejobs-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut map = OccupancyMap::new(0.1, SensorModel::default()).unwrap();
        map.set_value(VoxelCoord::new(1, 2, 3), 40);
        let path = dir.join("m.vxm");
        let mut w = FileWorker::spawn().unwrap();
        let save = |w: &mut FileWorker, p: &std::path::Path| {
            w.submit(Job::Save {
                path: p.into(),
                file: mapfile::encode_map_parts(&map),
            })
            .unwrap()
        };
        save(&mut w, &path);
        w.submit(Job::Load { path: path.clone() }).unwrap();
        w.submit(Job::Load {
            path: dir.join("missing.vxm"),
        })
        .unwrap();
        let mut got = Vec::new();
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(20);
        while got.len() < 3 {
            assert!(std::time::Instant::now() < deadline, "jobs never finished");
            got.extend(w.try_done());
            std::thread::yield_now();
        }
        match &got[..] {
            [Done::Saved(_, Ok(())), Done::Loaded(_, Ok(loaded)), Done::Loaded(p, Err(e))] => {
                let (m, field) = &**loaded;
                assert!(field.is_none());
                assert_eq!(m.grid().get(VoxelCoord::new(1, 2, 3)), Some(40));
                assert!(
                    p.ends_with("missing.vxm") && e.contains("missing.vxm"),
                    "{e}"
                );
            }
            _ => panic!("jobs out of order or failed"),
        }
        // At exit: a save is waited for, a load that never ends (a FIFO nobody writes) is
        // not, nor a save queued behind it.
        let fifo = dir.join("never.fifo");
        assert!(std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success());
        let (second, third) = (dir.join("m2.vxm"), dir.join("m3.vxm"));
        save(&mut w, &second);
        w.submit(Job::Load { path: fifo.clone() }).unwrap();
        save(&mut w, &third);
        let left = w.finish();
        assert!(matches!(&left[..], [Done::Saved(p, Ok(()))] if *p == second));
        assert!(second.exists());
        // Unblock the stuck worker (it then writes the third save and ends).
        drop(std::fs::OpenOptions::new().write(true).open(&fifo));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
