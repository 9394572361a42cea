"""The model commands of `vfdata` (registered through the `visionforce.commands` entry points)."""
