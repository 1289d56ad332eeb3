//! `skillaug view`: one self-contained HTML page ([`crate::view`]) that plays
//! back, from a run folder's ingested clips:
//!
//! * reference clips of `frames.parquet` (`--clip`, `--skill`; all clips
//!   when nothing else is asked for); missing frames are held and marked;
//! * STF samples of `stf_samples.parquet` (`--stf FILE`, `--traj K`): the
//!   start state, then the reference frames it tracks, the masked steps
//!   (inserted states s∅ and missing frames) marked in red;
//! * rollouts recorded by `skillaug eval --record N` (`--rollouts FILE|DIR`,
//!   `--trial K`), each beside its reference, on one clock.

use crate::export::motions::{gather, Selection};
use crate::sim::mjcf::Model;
use crate::view::{self, Item, ObjectView, Scene};
use anyhow::Result;
use std::path::{Path, PathBuf};

/// What to put on the page.
#[derive(Clone, Debug, Default)]
pub struct ViewRequest {
    /// The motions (of the run folder `select.from`).
    pub select: Selection,
    /// Data root (MJCF and object meshes); `None`: the default.
    pub data_root: Option<PathBuf>,
    /// The page to write.
    pub out: PathBuf,
}

/// Objects of the library's clips as one mesh pool; per clip, its indices.
struct Objects {
    pool: Vec<ObjectView>,
    names: Vec<String>,
}

impl Objects {
    fn of(&mut self, names: &[String], root: &Path) -> Result<Vec<usize>> {
        names
            .iter()
            .map(|n| {
                if let Some(k) = self.names.iter().position(|m| m == n) {
                    return Ok(k);
                }
                let spec = crate::sim::objects::ObjectSpec::load(n, root)?;
                self.pool.push(view::object_view(&spec));
                self.names.push(n.clone());
                Ok(self.pool.len() - 1)
            })
            .collect()
    }
}

/// Build the scene and write the page; returns the number of items.
pub fn run(req: &ViewRequest) -> Result<usize> {
    let lib = crate::table::load_library(&req.select.from)?;
    let root = crate::dataset::data_root(req.data_root.as_deref())?;
    let model = Model::for_skeleton(&root, lib.skeleton)?;
    let mut objs = Objects {
        pool: Vec::new(),
        names: Vec::new(),
    };
    let nob = lib.frames.first().map_or(0, |f| f.n_objects);
    let mut items = Vec::new();
    for m in gather(&lib, &req.select)? {
        let actors = m
            .tracks
            .iter()
            .map(|t| {
                view::actor(
                    &t.name,
                    &model,
                    nob,
                    &t.frames,
                    &t.masked,
                    t.value.as_deref().map(|v| ("SM", v)),
                )
            })
            .collect::<Result<Vec<_>>>()?;
        items.push(Item {
            title: m.title,
            skill: m.skill,
            note: m.note,
            fps: m.fps,
            objects: objs.of(&m.objects, &root)?,
            actors,
        });
    }

    let scene = Scene {
        title: format!("{} ({})", req.select.from.display(), lib.clips[0].dataset),
        bodies: view::bodies(&model)?,
        objects: objs.pool,
        items,
    };
    view::write(&scene, &req.out)?;
    Ok(scene.items.len())
}
