#!/usr/bin/python3
"""A cell PLC played by pymodbus (not Fettle's code), for interoperability tests.

Serves the register map of docs/plc-interface.md on 127.0.0.1 (port 0 = ephemeral) and
prints what it sees, one line each, flushed:
    listening 127.0.0.1:PORT
    fettle heartbeat running
    cycle request 42
    accepted 42
    state N
    result N
    command 3 sent
    command acknowledged
    slide to N
It raises one cycle request (--recipe) once Fettle's heartbeat runs, and after Fettle
accepts it sends one PackML command (--command, 0 = none). It acknowledges every result
it reads, and takes every slide command at once: the slide is at its target in the same
update that acknowledges the command (a move shorter than one of Fettle's polls).
Written for python3-pymodbus 3.0 (Debian 12).
"""
import argparse
import asyncio
import logging

from pymodbus.datastore import ModbusSequentialDataBlock, ModbusServerContext, ModbusSlaveContext
from pymodbus.server.async_io import ModbusTcpServer

HR = 3  # holding registers
# Offsets from register_base (docs/plc-interface.md).
VERSION, PLC_HB, REQ_TOGGLE, RECIPE, SLIDE_STATE, SLIDE_POS, CMD, CMD_TOGGLE, SLIDE_ACK, RESULT_ACK = range(10)
F_HB, F_ACK, F_STATE, F_SLIDE_TARGET, F_SLIDE_TOGGLE, F_RESULT, F_RESULT_TOGGLE, F_FAULT, F_LATCHED, F_CMD_ACK = range(
    16, 26
)
MAP_SIZE = 26


def say(text):
    print(text, flush=True)


async def run(args):
    base = args.register_base
    block = ModbusSequentialDataBlock(0, [0] * (base + MAP_SIZE))
    store = ModbusSlaveContext(hr=block, zero_mode=True)
    context = ModbusServerContext(slaves=store, single=True)
    server = ModbusTcpServer(context, address=("127.0.0.1", args.port), allow_reuse_address=True)
    serving = asyncio.create_task(server.serve_forever())
    await server.serving
    port = server.server.sockets[0].getsockname()[1]
    say(f"listening 127.0.0.1:{port}")

    def get(offset):
        return store.getValues(HR, base + offset, 1)[0]

    def put(offset, value):
        store.setValues(HR, base + offset, [value])

    put(VERSION, 2)
    put(SLIDE_STATE, 1)  # at home
    heartbeat = 0
    first_hb = None
    hb_running = False
    requested = accepted = command_sent = command_acked = False
    last_state = None
    while not serving.done():
        heartbeat = (heartbeat + 1) % 65536
        put(PLC_HB, heartbeat)
        hb = get(F_HB)
        if first_hb is None:
            first_hb = hb
        elif hb != first_hb and not hb_running:
            hb_running = True
            say("fettle heartbeat running")
        if hb_running and not requested:
            put(RECIPE, args.recipe)
            put(REQ_TOGGLE, 1)
            requested = True
            say(f"cycle request {args.recipe}")
        if requested and not accepted and get(F_ACK) == 1:
            accepted = True
            say(f"accepted {args.recipe}")
        state = get(F_STATE)
        if hb_running and state != last_state:
            last_state = state
            say(f"state {state}")
        if hb_running and get(F_RESULT_TOGGLE) != get(RESULT_ACK):
            say(f"result {get(F_RESULT)}")
            put(RESULT_ACK, get(F_RESULT_TOGGLE))
        if hb_running and get(F_SLIDE_TOGGLE) != get(SLIDE_ACK):
            target = get(F_SLIDE_TARGET)
            put(SLIDE_POS, target)
            put(SLIDE_STATE, 1 if target == 0 else 2)
            put(SLIDE_ACK, get(F_SLIDE_TOGGLE))
            say(f"slide to {target}")
        if accepted and args.command and not command_sent:
            put(CMD, args.command)
            put(CMD_TOGGLE, 1)
            command_sent = True
            say(f"command {args.command} sent")
        if command_sent and not command_acked and get(F_CMD_ACK) == 1:
            command_acked = True
            say("command acknowledged")
        await asyncio.sleep(args.heartbeat_period_ms / 1000.0)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, default=0)
    parser.add_argument("--register-base", type=int, default=0)
    parser.add_argument("--recipe", type=int, default=42)
    parser.add_argument("--command", type=int, default=0)
    parser.add_argument("--heartbeat-period-ms", type=int, default=20)
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    try:
        asyncio.run(run(args))
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
