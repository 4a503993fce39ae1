"""Registration: the options, the stages of a registration and the model identification."""
