//! Scene files: parse, validate, describe. See `docs/scene-format.md`.

mod desc;
mod error;
mod mesh_desc;

pub use desc::MAX_VALUE;
pub use desc::{
    Affine, CameraDesc, CameraKeyframe, CameraPose, FILE_MATERIALS, LightDesc, MAX_DEPTH,
    MAX_IMAGE_SIDE, MAX_SAMPLES, MaterialDesc, MeshDesc, MeshModel, Num, ObjectDesc,
    RenderSettings, Rotation, Scale, SceneDesc, Vec3, WorldDesc,
};
pub(crate) use desc::{check_colour, check_weight};
pub use error::{Location, SceneError};
