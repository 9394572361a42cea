"""Train, test and run the force models from YAML configs (Lightning's CLI): `vfmodels.training.train`.

    python train.py fit --config configs/visionforce.yaml
    python train.py test --config configs/visionforce.yaml --ckpt_path best
"""

from vfmodels.training.train import main

if __name__ == "__main__":
    main()
