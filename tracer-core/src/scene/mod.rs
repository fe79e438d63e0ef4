//! Scene files: parse, validate, describe. See `docs/scene-format.md`.

mod desc;
mod error;
mod mesh_desc;

pub use desc::{
    Affine, CameraDesc, CameraKeyframe, CameraPose, LightDesc, MaterialDesc, MeshDesc, MeshModel, Num, ObjectDesc, Rotation, Scale,
    FILE_MATERIALS, RenderSettings, SceneDesc, Vec3, WorldDesc, MAX_DEPTH,
    MAX_IMAGE_SIDE, MAX_SAMPLES,
};
pub use error::{Location, SceneError};
