"""Force estimation with a trained model: the model read from its checkpoint once (`trained_model`),
offline on a recording (`predict`, drawn by `overlay`), frame by frame (`live`, the streaming estimator),
a recording streamed through it (`stream`) and the live view (`live_session`)."""
