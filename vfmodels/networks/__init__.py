"""The force models: `set_transformer` (the proposed model), `baselines` (the paper's image baselines)
on `backbones`, the parts they share (`decoder`), `ridge` (a closed-form model on the same tokens) and
`registry` (the models a checkpoint may name)."""
