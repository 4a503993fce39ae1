"""Vehicle models: meshes, their metadata, the model library and the prepared-model store."""
