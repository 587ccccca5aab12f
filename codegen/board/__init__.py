"""Stage 1 of the pipeline: the board YAML read with positions (yamlsource), validated part by part against the
schema (model, schema) and as a whole against the chip's pin table and the board's rules (chips, rules), into one
`Board` (loader); every problem a located diagnostic (diagnostics)."""
