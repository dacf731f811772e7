"""Campaign folders, vendor imports and the Parquet dataset: data in and out of the pipeline."""
