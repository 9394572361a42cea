"""Force estimation with a trained model: offline on a recording (`predict`, drawn by `overlay`),
frame by frame (`live`, the streaming estimator), a recording streamed through it (`stream`) and the
live view (`live_session`)."""
