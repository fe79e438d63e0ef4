//! Scene files: parse, validate, describe. See `docs/scene-format.md`.

mod desc;
mod error;

pub use desc::{
    CameraDesc, CameraKeyframe, CameraPose, LightDesc, MaterialDesc, Num, ObjectDesc, RenderSettings, SceneDesc, Vec3, WorldDesc, MAX_DEPTH,
    MAX_IMAGE_SIDE, MAX_SAMPLES,
};
pub use error::{Location, SceneError};
