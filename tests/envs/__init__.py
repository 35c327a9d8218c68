"""The environment faces: Gymnasium's single and vector envs, PettingZoo's parallel env."""
