"""Robot datasets, normalisation statistics, image transforms and the Lightning datamodule."""
