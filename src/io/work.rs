//! The work folder: every file the stages, `lightfuse run` and `lightfuse evaluate` leave in it,
//! named once. docs/design.md §1 lists them; docs/formats.md gives their bytes.
//!
//! ```text
//! work/
//!   scene.glb  report.json  log.jsonl  checkpoint.json  poses.json  heldout/  train/   stage 1
//!   refined.glb  refine/{report.json, log.jsonl, checkpoint.json}                     stage 2
//!   relightable.glb  relightable.usda  invert/{report.json, log.jsonl, checkpoint.json, ...}  stage 3
//!   eval/{eval.json, eval.md, report.html, images/}                                   evaluate
//!   run.json                                                                          lightfuse run
//! ```
//!
//! Stage 1 keeps its files at the top of the folder (it was the first and only stage), the later
//! stages in a folder each; every path below is relative to the folder given on the command line.

use crate::error::{Error, Result};
use crate::io::dataset::Dataset;
use crate::scene::{Rigid, Scene, BACKGROUND};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// One stage's own files: its report, its loss log and its checkpoint, in `dir`.
#[derive(Clone, Debug, PartialEq)]
pub struct StageFiles {
    pub dir: PathBuf,
}

impl StageFiles {
    /// `report.json`: the stage's figures and settings.
    pub fn report(&self) -> PathBuf {
        self.dir.join("report.json")
    }

    /// `log.jsonl`: one line of losses per logged iteration.
    pub fn log(&self) -> PathBuf {
        self.dir.join("log.jsonl")
    }

    /// `checkpoint.json`: what `--resume` continues from.
    pub fn checkpoint(&self) -> PathBuf {
        self.dir.join("checkpoint.json")
    }
}

/// A work folder (`lightfuse run D -o WORK`, or the `work/` argument of each stage).
#[derive(Clone, Debug, PartialEq)]
pub struct WorkDir {
    root: PathBuf,
}

impl WorkDir {
    pub fn new(root: impl Into<PathBuf>) -> WorkDir {
        WorkDir { root: root.into() }
    }

    /// The folder itself.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Stage 1's scene (`lightfuse reconstruct`): geometry, SH appearance, object poses.
    pub fn scene(&self) -> PathBuf {
        self.root.join("scene.glb")
    }

    /// Stage 1's report, log and checkpoint (at the top of the folder).
    pub fn reconstruct(&self) -> StageFiles {
        StageFiles {
            dir: self.root.clone(),
        }
    }

    /// Stage 1's object poses step by step ([`PoseSteps`]).
    pub fn poses(&self) -> PathBuf {
        self.root.join("poses.json")
    }

    /// Stage 1's capture | render | error image of a held-out (`heldout/`) or training
    /// (`train/`) view.
    pub fn stage1_view(&self, held_out: bool, state: &str, view: usize) -> PathBuf {
        self.root.join(stage1_view_name(held_out, state, view))
    }

    /// Stage 2's scene (`lightfuse refine`): the geometry refined for ray tracing.
    pub fn refined(&self) -> PathBuf {
        self.root.join("refined.glb")
    }

    /// Stage 2's report, log and checkpoint (`refine/`).
    pub fn refine(&self) -> StageFiles {
        StageFiles {
            dir: self.root.join("refine"),
        }
    }

    /// Stage 3's scene (`lightfuse invert`): materials and the recovered environments.
    pub fn relightable(&self) -> PathBuf {
        self.root.join("relightable.glb")
    }

    /// Stage 3's scene as USD.
    pub fn relightable_usda(&self) -> PathBuf {
        self.root.join("relightable.usda")
    }

    /// Stage 3's report, log, checkpoint and images (`invert/`).
    pub fn invert(&self) -> StageFiles {
        StageFiles {
            dir: self.root.join("invert"),
        }
    }

    /// `lightfuse evaluate`'s folder: `eval.json`, `eval.md`, `report.html`, `images/`.
    pub fn eval_dir(&self) -> PathBuf {
        self.root.join("eval")
    }

    /// The evaluation's figures (Tables 1 and 2).
    pub fn eval_json(&self) -> PathBuf {
        self.eval_dir().join("eval.json")
    }

    /// The evaluation's tables as Markdown.
    pub fn eval_md(&self) -> PathBuf {
        self.eval_dir().join("eval.md")
    }

    /// The evaluation's report page.
    pub fn report_html(&self) -> PathBuf {
        self.eval_dir().join("report.html")
    }

    /// `lightfuse run`'s record of the settings the folder was made with.
    pub fn run_record(&self) -> PathBuf {
        self.root.join("run.json")
    }
}

/// `poses.json`: the poses of each object, `[j][o]` per training state (the reference state's
/// identities included), as item 4 of stage 1 found them (`stages::reconstruct::poses::estimate`): by point-cloud registration (none where it
/// failed), by the rendered alignment, each of the two polished by ICP in its own basin and
/// the better fit of the two (`register::Pair::best_fit`), and where training starts: that
/// pose or a polished turn of it about the vertical (`register::Pair::choose_turn`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PoseSteps {
    pub format: String,
    pub registered: Vec<Vec<Option<Rigid>>>,
    pub aligned: Vec<Vec<Rigid>>,
    /// Of the aligned and the registered pose, each polished (`register::Pair::polish`),
    /// the better geometric fit (`register::Pair::best_fit`).
    pub polished: Vec<Vec<Rigid>>,
    /// Where training starts: `register::Pair::choose_turn` of the polished pose.
    pub turned: Vec<Vec<Rigid>>,
}

impl PoseSteps {
    pub const FORMAT: &'static str = "lightfuse-stage1-poses/3";

    /// The record in `work`, if there is one of `states` x `objects` poses (a record of another
    /// dataset or an older format counts as none: it only adds figures to the report).
    pub fn read(work: &WorkDir, states: usize, objects: usize) -> Option<PoseSteps> {
        let p: PoseSteps = serde_json::from_slice(&std::fs::read(work.poses()).ok()?).ok()?;
        let fits = |lens: Vec<usize>| lens.len() == states && lens.iter().all(|&l| l == objects);
        (p.format == Self::FORMAT
            && fits(p.registered.iter().map(Vec::len).collect())
            && fits(p.aligned.iter().map(Vec::len).collect())
            && fits(p.polished.iter().map(Vec::len).collect())
            && fits(p.turned.iter().map(Vec::len).collect()))
        .then_some(p)
    }
}

/// The name, relative to the work folder, of stage 1's image of a held-out or training view
/// (what its report lists).
pub fn stage1_view_name(held_out: bool, state: &str, view: usize) -> String {
    let dir = if held_out { "heldout" } else { "train" };
    format!("{dir}/{state}_{view:03}.png")
}

/// An earlier stage's scene, checked against the dataset: the same objects (names and mask ids)
/// and a state for every training state. `missing` says how to make it when the file is absent.
pub fn read_stage_scene(path: &Path, dataset: &Dataset, missing: &str) -> Result<Scene> {
    if !path.is_file() {
        return Err(Error::invalid(
            path,
            "scene",
            format!("expected an earlier stage's scene here: {missing}"),
        ));
    }
    let scene = crate::io::read_scene(path)?;
    if scene.components.first().map(|c| c.name.as_str()) != Some(BACKGROUND) {
        return Err(Error::invalid(
            path,
            "components[0]",
            format!("expected the {BACKGROUND:?} component first, as stage 1 writes it"),
        ));
    }
    let objects: Vec<(&str, u32)> = scene.components[1..]
        .iter()
        .map(|c| (c.name.as_str(), c.id))
        .collect();
    let want: Vec<(&str, u32)> = dataset
        .objects
        .iter()
        .map(|o| (o.name.as_str(), o.id))
        .collect();
    if objects != want {
        return Err(Error::invalid(
            path,
            "components",
            format!(
                "expected the dataset's objects {want:?} (name, mask id) in its order, found {objects:?}; was this scene made from {}?",
                dataset.file.display()
            ),
        ));
    }
    for k in dataset.train_states() {
        let name = &dataset.states[k].name;
        if scene.state_index(name).is_none() {
            return Err(Error::invalid(
                path,
                "states",
                format!("expected a state named {name:?} (a training state of the dataset)"),
            ));
        }
    }
    Ok(scene)
}
