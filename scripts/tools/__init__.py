"""Tools: the face-model build, the data split, drills of failure cases, checks of the web app."""
