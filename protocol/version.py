"""The wire contract's version: (major, minor), and what each minor version added. A peer of
another major version is refused; a newer minor may add optional fields, which an older peer
ignores, and an older peer's messages decode with those fields at their defaults."""

from __future__ import annotations

PROTOCOL_VERSION: tuple[int, int] = (1, 11)
PROTOCOL_HISTORY: tuple[tuple[str, str], ...] = (
    (
        "1.0",
        "First wire protocol: status, open/join, reset, batched actions and steps, close, "
        "world frames for spectators, error replies.",
    ),
    (
        "1.1",
        "World frames carry each agent's reward terms (reward_terms, reward_term_names); "
        "a 1.0 peer's frames decode with none.",
    ),
    (
        "1.2",
        "Actions carry the trainer's step count (trainer_step) and world frames repeat it, so "
        "a spectator's recording shares the trainers' step timeline; world frames carry each "
        "vehicle's half length and width and each agent's heading. Older peers' messages decode "
        "with -1 and None.",
    ),
    (
        "1.3",
        "Actions may take some of the trainer's cars off the road until their arena is reset "
        "(retire: PettingZoo's finished agents); Opened says the server's minor version "
        "(server_minor), so a trainer can tell a server that would ignore retire. A 1.2 "
        "peer's Actions decode with no retired cars, its Opened with server_minor 2.",
    ),
    (
        "1.4",
        "Status replies say what waits in the server's queues (queued_actions, "
        "queued_requests) and how many frames a flood lost at their bounds (dropped_frames); "
        "a request beyond the bound is answered server_busy at once instead of not at all. "
        "A 1.3 server's status decodes with zeros.",
    ),
    (
        "1.5",
        "The behaviour spec states what a consumer needs to read the observations as typed "
        "fields: the road (RoadSpec: lanes and their width), the car (CarSpec: length, width, "
        "the speeds its actions move between) and per observation its named columns (the ego "
        "vector's fields) and its reach (Reach: metres ahead, behind, to the side, range). "
        "config_json stays, a record of the server's configuration that no consumer reads. A "
        "1.4 server's spec decodes without them, and clients refuse it.",
    ),
    (
        "1.6",
        "Steps through shared memory for a trainer on the server's host: an OpenRequest may "
        "say the trainer can read a segment (shm), the Opened offers one (ShmOffer: name, "
        "nonce, size), and once the trainer's Actions say it reads it (shm), the server writes "
        "each round's arrays there and sends a small StepsInShm notice instead of the Steps "
        "frame. Older peers' messages decode with no offer and no request, and get Steps "
        "frames as before.",
    ),
    (
        "1.7",
        "The shared-memory channel carries whole rounds: the offer's layout (ShmOffer.layout) "
        "says once where every array lies, the trainer writes its Actions into the segment "
        "and the server its Steps, and each side rings a futex doorbell in the segment's "
        "header instead of sending a Zenoh message; what is not a round (an error) still "
        "goes over Zenoh, counted in the header. The StepsInShm notice is gone: a 1.7 "
        "trainer declines a 1.6 offer (it has no layout), a 1.6 trainer refuses a 1.7 "
        "segment by its magic, and both keep to Steps over Zenoh.",
    ),
    (
        "1.8",
        "A trainer alone in its group may keep the group's whole state between rounds "
        "(SnapshotRequest, reply GroupState: opaque bytes) and put it back later, on this "
        "server or another of the same configuration (RestoreRequest, reply Steps): a remote "
        "run resumes exactly. A 1.7 server answers both with an error; a trainer reads "
        "Opened.server_minor before asking.",
    ),
    (
        "1.9",
        "An OpenRequest may carry the configuration an episode record was made on "
        "(as_recorded, its header's JSON): the server builds the simulator as it was then, "
        "from its own settings' history, or refuses, naming what differs; so a replay needs "
        "no knowledge of the server's settings on the trainer's side. A 1.8 server ignores "
        "the field; a trainer replaying a record refuses a server older than 1.9.",
    ),
    (
        "1.10",
        "The negotiation names a transport: an OpenRequest lists the channels besides Zenoh "
        "the trainer can take its rounds through (transports, preferred first) and the Opened "
        "offers at most one (offer: a ChannelOffer tagged with its transport's name, today "
        "shm's ShmOffer). Both sides still fill the 1.6 fields (OpenRequest.shm, Opened.shm), "
        "so a 1.9 peer negotiates shared memory as before. An OpenRequest may name the "
        "observations the trainer reads (observations): the server turns the other sensors "
        "off, or refuses one that is not on; a 1.9 server ignores the field and sends every "
        "observation.",
    ),
    (
        "1.11",
        "A trainer asks for what it reads by typed fields, not by the server's setting names: "
        "an OpenRequest may name the ego vector's fields it reads (ego_fields) and carry a "
        "configuration in another simulator's words (translation: highway-env's config dict, "
        "by the translation's name), which the server translates beside its scene exactly as "
        "the in-process simulator does. An observation's spec says how its normalised columns "
        "were scaled (scales: ColumnScale, the range each maps to [-1, 1]), so a consumer reads "
        "the quantities back without a copy of the server's defaults. A 1.10 server ignores "
        "the new fields (a client that sends them refuses it) and its specs decode without "
        "scales.",
    ),
)
# The minor version that builds a record's simulator again (OpenRequest.as_recorded).
AS_RECORDED_SINCE_MINOR = 9
# The minor version that keeps and restores a group's state (SnapshotRequest, RestoreRequest).
GROUP_STATE_SINCE_MINOR = 8
# The minor version whose spec carries the road, the car and the observations' facts.
TYPED_SPEC_SINCE_MINOR = 5
# The minor version that takes the ego fields and a translated configuration in an
# OpenRequest, and sends the observations' scales in the spec.
REQUESTED_READING_SINCE_MINOR = 11
