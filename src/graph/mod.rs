//! Graph files: YAML pipelines, validated before any process starts.
