//! The paper's stages, each a plain function of files (docs/design.md §4).

pub mod common;
pub mod invert;
pub mod pipeline;
pub mod reconstruct;
pub mod refine;

/// Every stage's settings come as two presets: `fast`, budgeted for a 2-core machine (minutes
/// on the demo, about an hour a stage on a preset room), and `paper`, the paper's own settings
/// (hours here). `lightfuse run` and each stage's command take `--preset`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Preset {
    #[default]
    Fast,
    Paper,
}

impl Preset {
    /// The name on the command line and in `run.json`.
    pub fn name(self) -> &'static str {
        match self {
            Preset::Fast => "fast",
            Preset::Paper => "paper",
        }
    }

    /// The preset's value of `fast` or `paper` (each stage's `Settings::fast` / `paper`).
    pub fn pick<T>(self, fast: fn() -> T, paper: fn() -> T) -> T {
        match self {
            Preset::Fast => fast(),
            Preset::Paper => paper(),
        }
    }
}
