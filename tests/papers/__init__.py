"""The three papers' set-ups as presets (Min et al., Ho, Fayjie et al.) and Min's ablation."""
