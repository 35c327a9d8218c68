"""Helpers the tests import (scripted scenes, real processes) and the trainer they run."""
