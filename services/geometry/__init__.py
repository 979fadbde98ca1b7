"""Pure numpy/OpenCV geometry shared by every estimator; imports nothing of artrack's."""
