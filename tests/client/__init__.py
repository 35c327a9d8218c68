"""overtake.client: policies, episodes, the scenario, the spectator and the ML-Agents bridge."""
