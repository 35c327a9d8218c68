"""The learner: the Q-networks (one description per network kind), the DQN family's objective
and its switches (double, dueling, n-step, prioritized replay), the optimisers, the replay
memory, and the members' learner that trains several runs' networks as one."""
