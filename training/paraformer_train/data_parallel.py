"""Two-process data parallelism for the CPU training step, measured by
``bench_data_parallel.py`` and not used by ``train.py``: on this machine's two cores it ran at
0.92× the one-process step of two threads (training/README.md, "Two processes of one thread").

Rank 0 holds the model and the optimiser. A helper process (rank 1) holds a copy of the model;
each step it gets half of the batch through a pipe and rank 0's weights and BatchNorm buffers
by a gloo broadcast (so the copies never drift), and the two ranks sum their gradients with
one gloo all-reduce.

The step is the one-process step, split: each half's loss divides by the whole batch's label
counts (``train.nll_loss(counts=...)``), so the two gradients sum to the whole batch's
gradient, and BatchNorm's batch statistics are the whole batch's (summed over both ranks by a
differentiable all-reduce, forward and backward). What differs is the order of
floating-point sums.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import socket
import sys
import types

import torch
import torch.distributed as dist

from .model import BatchNorm, Matcher, log_optimal_transport, log_optimal_transport_last_grad

SINKHORN = {"last": log_optimal_transport_last_grad, "full": log_optimal_transport}


def split_batch(bt: dict, parts: int) -> list[dict]:
    """``parts`` consecutive slices of a batch along its first axis (the pairs); each part gets
    at least one pair, so ``parts`` must not exceed the batch size."""
    n = len(bt["gt0"])
    if not 1 <= parts <= n:
        raise ValueError(f"cannot split a batch of {n} pairs into {parts} parts")
    bounds = [round(i * n / parts) for i in range(parts + 1)]
    return [{k: v[a:b] for k, v in bt.items()} for a, b in zip(bounds[:-1], bounds[1:])]


class _SumOverRanks(torch.autograd.Function):
    """All-reduce (sum) whose gradient is the all-reduce of the gradients: each rank's output
    is the same sum, so each rank's input gets the sum of what every rank's output received."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        out = x.clone()
        dist.all_reduce(out)
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        out = grad.contiguous().clone()
        dist.all_reduce(out)
        return out


def _synced_batch_norm(self: BatchNorm, x: torch.Tensor) -> torch.Tensor:
    """``BatchNorm.forward`` in training mode with the statistics of the whole batch over all
    ranks (two-pass mean and biased variance, as BatchNorm computes them); the running
    statistics are updated from them with BatchNorm's unbiased variance and momentum."""
    if not self.training:
        return BatchNorm.forward(self, x)
    xf = x.float()
    count = torch.tensor([float(xf.shape[0] * xf.shape[1])])
    total = _SumOverRanks.apply(torch.cat([xf.sum((0, 1)), count]))
    n = total[-1]
    mean = total[:-1] / n
    var = _SumOverRanks.apply(((xf - mean) ** 2).sum((0, 1))) / n
    with torch.no_grad():
        m = self.momentum
        self.running_mean.mul_(1 - m).add_(mean.detach(), alpha=m)
        self.running_var.mul_(1 - m).add_(var.detach() * (n / (n - 1)), alpha=m)
        self.num_batches_tracked.add_(1)
    y = (xf - mean) * torch.rsqrt(var + self.eps) * self.weight + self.bias
    return y.to(x.dtype)


def sync_batch_norms(model: torch.nn.Module) -> None:
    """Every ``BatchNorm`` of ``model`` normalises with the statistics over all ranks."""
    for mod in model.modules():
        if isinstance(mod, BatchNorm):
            mod.forward = types.MethodType(_synced_batch_norm, mod)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _state_vector(model: torch.nn.Module) -> torch.Tensor:
    return torch.cat([t.detach().reshape(-1).double() for t in model.state_dict().values()])


def _load_state_vector(model: torch.nn.Module, flat: torch.Tensor) -> None:
    at = 0
    with torch.no_grad():
        for t in model.state_dict().values():  # views of the parameters and buffers
            t.copy_(flat[at: at + t.numel()].view_as(t).to(t.dtype))
            at += t.numel()


def _reduce_gradients(model: torch.nn.Module, loss: float) -> float:
    """Sums every parameter's gradient (and the loss) over the ranks; a parameter without a
    gradient on every rank keeps none, as in a one-process step (AdamW skips it)."""
    params = list(model.parameters())
    parts = [p.grad.reshape(-1) if p.grad is not None else torch.zeros(p.numel()) for p in params]
    present = torch.tensor([float(p.grad is not None) for p in params])
    flat = torch.cat(parts + [present, torch.tensor([loss])])
    dist.all_reduce(flat)
    at = 0
    for p, has in zip(params, flat[-1 - len(params): -1]):
        p.grad = flat[at: at + p.numel()].view_as(p).clone() if has > 0 else None
        at += p.numel()
    return float(flat[-1])


def _helper(conn, training_dir: str, port: int, cfg: dict, sinkhorn: str, iters: int, bf16: bool,
            threads: int) -> None:
    sys.path.insert(0, training_dir)
    from train import matching_losses  # noqa: E402  (train.py's own loss, not a copy)

    torch.set_num_threads(threads)
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=1, world_size=2)
    model = Matcher(cfg).train()
    sync_batch_norms(model)
    flat = _state_vector(model)
    try:
        while True:
            msg = conn.recv()
            if msg is None:
                break
            part, counts = msg
            dist.broadcast(flat, 0)
            _load_state_vector(model, flat)
            model.zero_grad(set_to_none=True)
            loss = matching_losses(model, None, part, SINKHORN[sinkhorn], iters, bf16, counts)[-1]
            loss.backward()
            _reduce_gradients(model, loss.item())
    finally:
        dist.destroy_process_group()


class DataParallel:
    """Rank 0's side: ``step`` sends ``model``'s weights to rank 1 and computes the gradient of
    a batch over both ranks into ``model``'s ``.grad``. ``model``'s BatchNorms are synced
    (``sync_batch_norms``): its forward in training mode belongs inside ``step``. ``close``
    (or leaving a ``with`` block) stops the helper."""

    def __init__(self, model: Matcher, cfg: dict, sinkhorn: str, iters: int, bf16: bool, threads: int = 1):
        if sinkhorn not in SINKHORN:
            raise ValueError(f"sinkhorn gradient {sinkhorn!r}: expected one of {sorted(SINKHORN)}")
        self.model, self.sinkhorn, self.iters, self.bf16 = model, sinkhorn, iters, bf16
        port = _free_port()
        ctx = mp.get_context("spawn")
        self.conn, child = ctx.Pipe()
        training_dir = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        self.proc = ctx.Process(target=_helper, args=(child, training_dir, port, cfg, sinkhorn, iters, bf16, threads),
                                daemon=True)
        self.proc.start()
        dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=0, world_size=2)
        sync_batch_norms(model)

    def step(self, bt: dict) -> float:
        """Forward and backward of ``bt`` split over both ranks; returns the whole batch's loss."""
        from train import label_counts, matching_losses  # train.py's own loss

        if not self.proc.is_alive():
            raise RuntimeError(f"the data-parallel helper process exited (code {self.proc.exitcode})")
        counts = label_counts(bt)
        mine, theirs = split_batch(bt, 2)
        self.conn.send((theirs, counts))
        dist.broadcast(_state_vector(self.model), 0)
        self.model.zero_grad(set_to_none=True)
        loss = matching_losses(self.model, None, mine, SINKHORN[self.sinkhorn], self.iters, self.bf16, counts)[-1]
        loss.backward()
        return _reduce_gradients(self.model, loss.item())

    def close(self) -> None:
        if self.proc.is_alive():
            try:
                self.conn.send(None)
            except (BrokenPipeError, OSError):
                pass
            self.proc.join(timeout=30)
        if self.proc.is_alive():
            self.proc.terminate()
        if dist.is_initialized():
            dist.destroy_process_group()

    def __enter__(self) -> "DataParallel":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
