"""The learner of several runs at once: S members' networks stacked into one
(:mod:`.member_network`), one forward pass acting for every member, one backward pass and one
optimiser step (:mod:`.member_optim`) updating every member on its own batch.

Member k is what a lone :class:`.learner.DQNLearner` of the same config and seed is: its
network starts from the same seed, its loss is its own batch's mean (the members' losses are
summed, so each member's gradient is its own loss's), its gradients are clipped by its own
norm, its optimiser has its own learning rate and moments, its target network is copied on
its own schedule, and it explores with its own generator. An update of member k equals a lone
learner's update on the same batch up to float rounding (tests/trainers/test_members.py).

Members share an architecture (the network's shapes), the algorithm, the optimiser's kind, the
batch size and the device; they may differ in seed, learning rate and any other setting that
leaves the shapes alone. :meth:`MembersLearner.member_state_dict` is member k's state as a lone
learner's ``state_dict``, so a member's checkpoint is a lone run's.
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from .dqn_config import AlgoSpec, DQNConfig
from .heads import HeadSpec, legacy_state
from .learner import (
    AnyShape,
    Precision,
    autocast,
    build_network,
    build_optimizer,
    epsilon_greedy,
    execution_device,
)
from .member_network import (
    load_member_state,
    member_parameter_names,
    member_state,
    stacked_network,
)
from .member_optim import MemberOptimizer, shared_setting
from .network import Inputs
from .objectives import Objective, QuantileObjective, TDObjective, Transitions
from .replay_memory import ReplayBatch


class MembersLearner:
    """S members' online and target networks, stacked; acting and updating all at once."""

    def __init__(
        self,
        shape: AnyShape,
        inputs: Inputs,
        configs: Sequence[DQNConfig],
        algo: AlgoSpec,
        seeds: Sequence[int],
        *,
        device: str = "cpu",
        precision: Precision = "fp32",
    ) -> None:
        if len(configs) != len(seeds) or not configs:
            raise ValueError(f"one config per member seed, got {len(configs)} and {len(seeds)}")
        if precision == "fp16":
            raise ValueError("members train in fp32 or bf16 (fp16's loss scaling is a lone run's)")
        self.shape, self.inputs, self.algo = shape, inputs, algo
        self.configs = tuple(configs)
        self.members = len(configs)
        self.batch_size: int = shared_setting(configs, "batch_size")
        for name in ("network", "stack", "lstm_cells", "hidden_units", "quantiles", "loss"):
            shared_setting(configs, name)
        self.device = execution_device(device, precision)
        self.precision = precision
        head = HeadSpec(algo.head, quantiles=configs[0].quantiles)
        lones = []
        self.torch_rng_states = []
        for seed, config in zip(seeds, configs, strict=True):
            torch.manual_seed(seed)  # as a lone run seeds its network
            lones.append(build_network(shape, inputs, config, head))
            self.torch_rng_states.append(torch.get_rng_state())
        self._lone = lones[0]  # a lone network's layout, for the optimiser's state dicts
        self.online = stacked_network(lones).to(self.device)
        self.target = copy.deepcopy(self.online).eval()
        for p in self.target.parameters():
            p.requires_grad_(False)
        self.optimizer = MemberOptimizer(list(self.online.parameters()), configs)
        network: Any = self.online
        self.head = network.head
        first = configs[0]
        self.objective: Objective = (
            QuantileObjective(self.head, algo.double, first.quantile_kappa)
            if algo.head == "quantile"
            else TDObjective(self.head, algo.double, first.loss, first.huber_delta)
        )
        self.input_names: tuple[str, ...] = network.input_names
        self.used_inputs = set(network.used_inputs)
        self.gammas = np.array([c.gamma for c in configs], dtype=np.float64)
        self.updates = np.zeros(self.members, dtype=np.int64)

    # --- inputs ---------------------------------------------------------------------------

    def _tensors(self, obs: Sequence[dict[str, np.ndarray]]) -> list[torch.Tensor | None]:
        """The members' observations as the stacked network's rows, member-major."""
        return [
            torch.as_tensor(np.concatenate([o[name] for o in obs]), device=self.device)
            if name in self.used_inputs
            else None
            for name in self.input_names
        ]

    def _autocast(self) -> contextlib.AbstractContextManager[Any]:
        return autocast(self.device, self.precision)

    # --- acting ---------------------------------------------------------------------------

    @torch.no_grad()
    def q_values(self, obs: Sequence[dict[str, np.ndarray]]) -> list[np.ndarray]:
        """Each member's (N, actions) Q-values of its stacked observations."""
        if self.online.training:  # train()/eval() walk every module: only when it changes
            self.online.eval()
        with self._autocast():
            q = self.head.q(self.online(*self._tensors(obs)))
        return np.split(q.float().cpu().numpy(), self.members)

    def act(
        self,
        obs: Sequence[dict[str, np.ndarray]],
        masks: Sequence[np.ndarray],
        epsilons: Sequence[float],
        rngs: Sequence[np.random.Generator],
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each member's epsilon-greedy actions and Q-values, as
        :meth:`.learner.DQNLearner.act` gives a lone run's (member k with its own epsilon and
        generator)."""
        return [
            epsilon_greedy(q, mask, epsilon, rng)
            for q, mask, epsilon, rng in zip(self.q_values(obs), masks, epsilons, rngs, strict=True)
        ]

    # --- learning -------------------------------------------------------------------------

    def update(self, batches: Sequence[ReplayBatch | None]) -> list[dict[str, Any]]:
        """One gradient step of every member on its own batch (``batches[k]`` member k's);
        returns each member's stats as :meth:`.learner.DQNLearner.update` does. A member whose
        batch is None sits the update out: its network, moments and counts stay as they were
        (its stats are empty)."""
        if len(batches) != self.members:
            raise ValueError(f"one batch per member ({self.members}), got {len(batches)}")
        given = [b for b in batches if b is not None]
        if not given:
            raise ValueError("an update needs at least one member's batch")
        resting = [k for k, b in enumerate(batches) if b is None]
        kept = self._kept(resting) if resting else None
        full = [given[0] if b is None else b for b in batches]
        stats = self._update(full)
        if kept is not None:
            self._put_back(resting, kept)
            for k in resting:
                stats[k] = {}
        return stats

    @torch.no_grad()
    def _kept(self, members: list[int]) -> list[torch.Tensor]:
        """Copies of ``members``' parameters and optimiser state (:meth:`_put_back`)."""
        index = torch.as_tensor(members, dtype=torch.long, device=self.device)
        tensors = [
            *self.online.parameters(),
            *(t for ts in self.optimizer.state.values() for t in ts),
        ]
        return [t.index_select(0, index) for t in tensors] + [self.optimizer.steps[members].clone()]

    @torch.no_grad()
    def _put_back(self, members: list[int], kept: list[torch.Tensor]) -> None:
        index = torch.as_tensor(members, dtype=torch.long, device=self.device)
        tensors = [
            *self.online.parameters(),
            *(t for ts in self.optimizer.state.values() for t in ts),
        ]
        for tensor, saved in zip(tensors, kept[:-1], strict=True):
            tensor.index_copy_(0, index, saved)
        self.optimizer.steps[members] = kept[-1]
        self.updates[members] -= 1

    def _update(self, batches: Sequence[ReplayBatch]) -> list[dict[str, Any]]:
        if not self.online.training:
            self.online.train()
        dev, size = self.device, self.batch_size
        for batch in batches:
            if len(batch.action) != size:
                raise ValueError(
                    f"members' batches hold {size} transitions, got {len(batch.action)}"
                )
        steps = np.concatenate([b.steps for b in batches])
        gamma = torch.as_tensor(
            np.repeat(self.gammas, size) ** steps, device=dev, dtype=torch.float32
        )
        transitions = Transitions(
            action=torch.as_tensor(np.concatenate([b.action for b in batches]), device=dev),
            reward=torch.as_tensor(
                np.concatenate([b.reward for b in batches]), device=dev, dtype=torch.float32
            ),
            terminated=torch.as_tensor(np.concatenate([b.terminated for b in batches]), device=dev),
            next_mask=torch.as_tensor(np.concatenate([b.next_mask for b in batches]), device=dev),
            gamma=gamma,
        )
        with self._autocast():
            online = self.online(*self._tensors([b.obs for b in batches]))
        with torch.no_grad():
            next_inputs = self._tensors([b.next_obs for b in batches])
            with self._autocast():
                next_target = self.target(*next_inputs)
                next_online = self.online(*next_inputs) if self.algo.double else None
        terms = self.objective.terms(online, next_target, next_online, transitions)
        each = terms.loss
        weighted = [b.weight is not None for b in batches]
        if any(weighted):
            if not all(weighted):
                raise ValueError("members' batches are all prioritized or none")
            weight = np.concatenate([b.weight for b in batches if b.weight is not None])
            each = each * torch.as_tensor(weight, device=dev, dtype=torch.float32)
        member_loss = each.reshape(self.members, size).mean(dim=1)
        self.optimizer.zero_grad()
        member_loss.sum().backward()
        self.optimizer.clip_gradients()
        self.optimizer.step()
        self.updates += 1
        # One copy to the host for every member's figures.
        q_taken = terms.q_taken.reshape(self.members, size).mean(dim=1)
        figures = torch.stack([member_loss.detach(), q_taken]).cpu().numpy()
        stats: list[dict[str, Any]] = [
            {"loss": float(figures[0, k]), "q_taken": float(figures[1, k])}
            for k in range(self.members)
        ]
        if any(weighted):
            td = terms.td_error.cpu().numpy().reshape(self.members, size)
            for k, member in enumerate(stats):
                member["td_error"] = td[k]
        return stats

    @torch.no_grad()
    def sync_target(self, members: Sequence[int]) -> None:
        """Copy ``members``' online networks into their target networks."""
        index = torch.as_tensor(list(members), dtype=torch.long, device=self.device)
        names = member_parameter_names(self.online)
        target = dict(self.target.named_parameters())
        for name, param in self.online.named_parameters():
            if name in names:
                target[name].index_copy_(0, index, param.index_select(0, index))

    # --- persistence: a member as a lone learner ------------------------------------------

    def _lone_optimizer(self, member: int) -> torch.optim.Optimizer:
        return build_optimizer(copy.deepcopy(self._lone).parameters(), self.configs[member])

    def member_state_dict(self, member: int) -> dict[str, Any]:
        """Member ``member``'s state as :meth:`.learner.DQNLearner.state_dict` gives a lone
        learner's."""
        return {
            "online": member_state(self.online, member),
            "target": member_state(self.target, member),
            "optimizer": self.optimizer.member_state_dict(member, self._lone_optimizer(member)),
            "updates": int(self.updates[member]),
        }

    def load_member_state_dict(self, member: int, state: dict[str, Any]) -> dict[str, bool]:
        """Member ``member`` from a lone learner's state dict (as
        :meth:`.learner.DQNLearner.load_state_dict` restores one); returns which parts were
        restored (``target``, ``optimizer``)."""
        online = legacy_state(state["online"])
        load_member_state(self.online, member, online)
        restored = {"target": "target" in state, "optimizer": "optimizer" in state}
        load_member_state(
            self.target, member, legacy_state(state["target"]) if restored["target"] else online
        )
        if restored["optimizer"]:
            self.optimizer.load_member_state_dict(
                member, self._lone_optimizer(member), state["optimizer"]
            )
        self.updates[member] = int(state.get("updates", 0))
        return restored
