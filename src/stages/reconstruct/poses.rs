//! Stage 1's object poses (item 4 of the stage; the paper's eq. state-assembly places each
//! object by them): every object's rigid motion from the reference state into each training
//! state, found from the captures alone before training starts, in four recorded steps
//! ([`PoseSteps`], `poses.json`, a work-folder file): point-cloud registration ([`super::register`]), alignment by
//! rendering ([`super::align`]), an ICP polish of both that keeps the better geometric fit, and
//! a choice among turns about the vertical that the texture decides. `--oracle-poses` takes
//! the dataset's instead ([`oracle`]).

use super::init::{ObjectRef, PointCloud};
use super::{align, register};
use crate::error::Result;
use crate::io::dataset::{Dataset, Observation};
use crate::io::work::PoseSteps;
use crate::scene::Rigid;
use glam::Vec3;

/// The dataset's ground-truth poses relative to the reference state (`--oracle-poses`; an
/// evaluation aid, not a capture's information).
pub fn oracle(
    dataset: &Dataset,
    train_states: &[usize],
    objects: &[ObjectRef],
) -> Result<Vec<Vec<Rigid>>> {
    train_states
        .iter()
        .map(|&k| {
            objects
                .iter()
                .map(|o| {
                    let ref_pose = dataset.object_pose(train_states[0], &o.name)?;
                    let pose = dataset.object_pose(k, &o.name)?;
                    Ok(pose.compose(&ref_pose.inverse()))
                })
                .collect::<Result<Vec<_>>>()
        })
        .collect()
}

/// Every object's pose in every training state from the captures: `clouds[j]` is state j's
/// back-projected training views, `train[j]` its observations, `ids` the objects' mask ids.
/// Training starts from [`PoseSteps::turned`].
pub fn estimate(clouds: &[PointCloud], train: &[Vec<Observation>], ids: &[u8]) -> PoseSteps {
    let ropts = register::RegisterOptions::default();
    // Each object's clouds in the reference state and in state j, prepared once for
    // the registration, the polish and the choice below.
    let pairs = register::object_pairs(clouds, ids, &ropts);
    let reg = register::registrations(&pairs);
    // The point-cloud registrations are candidates for the analysis-by-synthesis search,
    // which scores poses by rendering the object into every view of the state.
    let initial: Vec<Vec<Option<Rigid>>> = reg
        .iter()
        .map(|row| row.iter().map(|r| r.map(|r| r.transform)).collect())
        .collect();
    let refs = align::median_footprint(&train[0], ids)
        .map(|voxel| align::reference_surfels(&train[0], ids, voxel));
    let aligned: Vec<Vec<Rigid>> = match refs {
        Some(refs) => align::object_poses_by_rendering(
            &refs,
            ids,
            train,
            &initial,
            &align::AlignOptions::default(),
        ),
        None => initial
            .iter()
            .map(|row| row.iter().map(|r| r.unwrap_or(Rigid::IDENTITY)).collect())
            .collect(),
    };
    // Two hypotheses per object and state, each polished in its own basin by ICP
    // (`register::Pair::polish`): the rendered alignment's pose, which finds the basin
    // where registration lost the object (study: a thin sign, a chrome bottle upside
    // down; bedroom: a lamp 65° off) but is biased by ~1-2 cm and a few degrees, and
    // registration's estimate, right where the alignment's score chose a wrong basin
    // (study: an untextured Suzanne 136° off). The one whose geometry fits the clouds
    // best wins (`register::Pair::best_fit`; colour does not vote across lightings).
    // Then, where the shape ties turns about the vertical (a solid of revolution, a box
    // four ways), the texture decides between them (`register::Pair::choose_turn`).
    let limits = register::PolishLimits::default();
    let turn = register::TurnOptions::default();
    let (polished, turned): (Vec<Vec<Rigid>>, Vec<Vec<Rigid>>) = aligned
        .iter()
        .enumerate()
        .map(|(j, row)| {
            row.iter()
                .enumerate()
                .map(|(o, pose)| {
                    let Some(pair) = pairs[j][o].as_ref().filter(|_| j > 0) else {
                        return (*pose, *pose);
                    };
                    // Registration's estimate, where it lies in the basin the
                    // alignment chose, is a second start there.
                    let starts: Vec<Rigid> = std::iter::once(*pose).chain(initial[j][o]).collect();
                    let from_aligned = pair.polish(&starts, &limits).map_or(*pose, |r| r.transform);
                    let from_registered = initial[j][o]
                        .map(|r| pair.polish(&[r], &limits).map_or(r, |p| p.transform));
                    let hypotheses: Vec<Rigid> = std::iter::once(from_aligned)
                        .chain(from_registered)
                        .collect();
                    let polished = pair
                        .best_fit(&hypotheses)
                        .map_or(from_aligned, |(k, _)| hypotheses[k]);
                    let turned = pair
                        .choose_turn(&polished, Vec3::Y, &limits, &turn)
                        .transform;
                    (polished, turned)
                })
                .unzip()
        })
        .unzip();
    PoseSteps {
        format: PoseSteps::FORMAT.into(),
        registered: initial,
        aligned,
        polished,
        turned,
    }
}
