"""The road's rounds, in this process or in a server's group: the rounds and what each agent
slot carries between them, their snapshots, world frames, the behaviour spec, the in-process
engine and the Gymnasium and PettingZoo faces over it. Imports the simulation core only."""
