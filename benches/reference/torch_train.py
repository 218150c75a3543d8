"""PyTorch (eager, float32, CPU) reference of `scanloc bench train`: the same
network as scanloc's CNN (dilated 3x3 conv -> batch norm -> ReLU blocks
without conv bias, a 1x1 head with bias), the same initialisation scale
(He-normal convs, N(0, 0.01^2) head, score bias log(0.01/0.99)), the same
loss shape (CenterNet focal loss on channel 0, L1 offset loss on channels
1-2 of the supervised pixels) and Adam (lr 2e-3), on synthetic batches of
frames of the same size.

Times training steps (samples/s, after warm-up steps) and inference
(frames/s, `torch.inference_mode`, eval-mode batch norm, batches of
--inference-batch), in wall-clock and in CPU seconds of the process.
Prints `train_samples_per_second=`, `train_samples_per_cpu_second=`,
`frames_per_cpu_second=` and `frames_per_second=<number>` last.

glibc's malloc returns PyTorch's large activation buffers to the system
after every step unless told to keep them; the script sets
MALLOC_MMAP_THRESHOLD_ and MALLOC_TRIM_THRESHOLD_ (and the thread count of
OpenMP) and re-executes itself, since malloc reads them at start-up.
"""
import argparse
import math
import os
import sys
import time

KEPT_BUFFERS = {
    "MALLOC_MMAP_THRESHOLD_": "33554432",
    "MALLOC_TRIM_THRESHOLD_": "4294967296",
}


def reexec_with_environment(threads):
    wanted = dict(KEPT_BUFFERS, OMP_NUM_THREADS=str(threads))
    if all(os.environ.get(k) == v for k, v in wanted.items()):
        return
    env = dict(os.environ, **wanted)
    os.execve(sys.executable, [sys.executable] + sys.argv, env)


def parse():
    parser = argparse.ArgumentParser()
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--samples", type=int, default=2000)
    parser.add_argument("--locate-frames", type=int, default=2048)
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--inference-batch", type=int, default=256)
    parser.add_argument("--channels", type=int, default=32)
    parser.add_argument("--dilations", default="1,1,2,4,2,1")
    parser.add_argument("--input-channels", type=int, default=2)
    parser.add_argument("--output-channels", type=int, default=3)
    parser.add_argument("--height", type=int, default=24)
    parser.add_argument("--width", type=int, default=25)
    parser.add_argument("--emitters", type=int, default=7)
    parser.add_argument("--warmup-steps", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args()


def build(torch, args):
    nn = torch.nn
    layers = []
    in_channels = args.input_channels
    for dilation in [int(d) for d in args.dilations.split(",")]:
        conv = nn.Conv2d(
            in_channels, args.channels, 3, padding=dilation, dilation=dilation, bias=False
        )
        nn.init.normal_(conv.weight, 0.0, math.sqrt(2.0 / (in_channels * 9)))
        layers += [conv, nn.BatchNorm2d(args.channels, eps=1e-5, momentum=0.1), nn.ReLU()]
        in_channels = args.channels
    head = nn.Conv2d(in_channels, args.output_channels, 1, bias=True)
    nn.init.normal_(head.weight, 0.0, 0.01)
    with torch.no_grad():
        head.bias.zero_()
        head.bias[0] = math.log(0.01 / 0.99)
    return nn.Sequential(*layers, head)


def batch(torch, args, generator):
    """Normalised noise frames with an edge channel, and targets of the
    scanloc shape: Gaussian heat (sigma 1 px) around random emitters,
    positives at their pixels, offsets supervised within 1 px."""
    n, h, w = args.batch_size, args.height, args.width
    frames = torch.randn(n, 1, h, w, generator=generator)
    channels = [frames] + [torch.ones(n, 1, h, w)] * (args.input_channels - 1)
    inputs = torch.cat(channels, dim=1)
    ys = torch.rand(n, args.emitters, generator=generator) * (h - 1)
    xs = torch.rand(n, args.emitters, generator=generator) * (w - 1)
    rows = torch.arange(h).view(1, 1, h, 1).float()
    cols = torch.arange(w).view(1, 1, 1, w).float()
    d2 = (rows - ys.view(n, -1, 1, 1)) ** 2 + (cols - xs.view(n, -1, 1, 1)) ** 2
    heat = torch.exp(-d2 / 2).amax(dim=1, keepdim=True)
    positive = torch.zeros(n, 1, h, w)
    mask = torch.zeros(n, 1, h, w)
    for i in range(n):
        for r, c in zip(ys[i].round().long(), xs[i].round().long()):
            positive[i, 0, r, c] = 1.0
            mask[i, 0, max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2] = 1.0
    negative_weight = (1 - heat) ** 4 * (1 - positive)
    offset = torch.rand(n, 2, h, w, generator=generator) - 0.5
    return inputs, positive, negative_weight, offset, mask


def loss_of(torch, output, positive, negative_weight, offset_target, mask):
    logit = output[:, :1]
    offset = output[:, 1:3]
    probability = torch.sigmoid(logit)
    log_p = torch.nn.functional.logsigmoid(logit)
    log_not_p = torch.nn.functional.logsigmoid(-logit)
    positives = positive.sum().clamp(min=1)
    score = -(((1 - probability) ** 2) * log_p * positive
              + probability ** 2 * log_not_p * negative_weight).sum() / positives
    offsets = ((offset - offset_target).abs() * mask).sum() / mask.sum().clamp(min=1)
    return score + offsets


def main():
    args = parse()
    reexec_with_environment(args.threads)
    import torch

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    generator = torch.Generator().manual_seed(args.seed)
    model = build(torch, args)
    optimiser = torch.optim.Adam(model.parameters(), lr=2e-3)
    steps = max(1, math.ceil(args.samples / args.batch_size))
    batches = [batch(torch, args, generator) for _ in range(min(steps, 8))]

    def step(i):
        inputs, *targets = batches[i % len(batches)]
        optimiser.zero_grad(set_to_none=True)
        loss = loss_of(torch, model(inputs), *targets)
        loss.backward()
        optimiser.step()
        return loss

    model.train()
    for i in range(args.warmup_steps):
        step(i)
    start, cpu_start = time.perf_counter(), time.process_time()
    for i in range(steps):
        loss = step(i)
    loss.item()
    train_seconds = time.perf_counter() - start
    train_cpu_seconds = time.process_time() - cpu_start
    train_rate = steps * args.batch_size / train_seconds
    train_cpu_rate = steps * args.batch_size / train_cpu_seconds

    model.eval()
    frames = torch.cat([b[0] for b in batches])
    with torch.inference_mode():
        model(frames[: args.inference_batch])
        chunks = max(1, math.ceil(args.locate_frames / args.inference_batch))
        inputs = frames[: args.inference_batch]
        if inputs.shape[0] < args.inference_batch:
            repeat = math.ceil(args.inference_batch / inputs.shape[0])
            inputs = inputs.repeat(repeat, 1, 1, 1)[: args.inference_batch]
        start, cpu_start = time.perf_counter(), time.process_time()
        for _ in range(chunks):
            torch.sigmoid(model(inputs)[:, :1])
        locate_seconds = time.perf_counter() - start
        locate_cpu_seconds = time.process_time() - cpu_start
    locate_rate = chunks * args.inference_batch / locate_seconds
    locate_cpu_rate = chunks * args.inference_batch / locate_cpu_seconds

    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    print(f"train_samples_per_second={train_rate:.1f}")
    print(f"train_samples_per_cpu_second={train_cpu_rate:.1f}")
    print(f"frames_per_cpu_second={locate_cpu_rate:.1f}")
    print(f"frames_per_second={locate_rate:.1f}")


if __name__ == "__main__":
    main()
