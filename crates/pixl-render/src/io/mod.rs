//! Files shared with other tools: triangle meshes in and out ([`export`]: glTF binary, OBJ,
//! PLY; the scene loader reads mesh objects through [`export::load_mesh`]) and the Blender
//! bridge ([`blender`]: a scene → a Python script that rebuilds it in Blender and renders
//! Cycles' passes).
pub mod blender;
pub mod export;
