"""ML-Agents' own tools on overtake: the low-level ``BaseEnv`` over an overtake server
(:mod:`.environment`, with ML-Agents' types built without mlagents-envs: :mod:`.types`),
ML-Agents' Gym and PettingZoo wrappers without their registry download (:mod:`.wrappers`), and
``overtake-unity-bridge``, which speaks ML-Agents' gRPC wire (:mod:`.wire`) so that
``UnityEnvironment`` and ``mlagents-learn`` drive overtake as they drive a Unity scene
(:mod:`.unity_bridge`)."""
