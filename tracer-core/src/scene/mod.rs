//! Scene files: parse, validate, describe. See `docs/scene-format.md`.

pub mod adaptive;
mod desc;
mod error;
mod mesh_desc;
mod model_scene;
mod overrides;

pub use desc::MAX_VALUE;
pub use desc::{
    Affine, BsdfDesc, CameraDesc, CameraKeyframe, CameraPose, EnvironmentDesc, FILE_MATERIALS,
    Integrator, LightDesc, LightShape, MAX_DEPTH, MAX_IMAGE_SIDE, MAX_LIGHT_SAMPLES, MAX_SAMPLES,
    MaterialDesc, MeshDesc, MeshKeyframe, MeshModel, Num, ObjectDesc, PathLightKind,
    RenderSettings, Rotation, Scale, SceneDesc, SphereKeyframe, Vec3, WorldDesc,
};
pub(crate) use desc::{check_colour, check_weight};
pub use error::{Location, SceneError};
pub use model_scene::{
    AUTO_FOV_Y, CameraPick, DEFAULT_AMBIENT, DEFAULT_SKY, DIRECTIONAL_DISTANCE, HEADLIGHT,
    LightsPick, ModelSceneOptions, SceneInput, model_scene_text, with_environment,
};
pub use overrides::{RenderOverrides, SettingsError};
