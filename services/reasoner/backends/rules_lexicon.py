"""Which nouns can name something in a room: the rules parser's check on a candidate target (issue 33).

Two word lists and a rule. `PHYSICAL` holds the perception vocabulary (the simulator's catalogue names, their
word synonyms and families, kept equal to services/perception/query.py by tests/reasoner/test_rules_parse.py;
the reasoner may not import another service) and everyday physical-object nouns. `NOT_OBJECTS` holds nouns a
command uses that no room contains: time and manner ("take your time", "with care", "in a hurry"), amounts and
units ("a bit", "one metre"), abstract things ("the answer", "the initiative"). A noun in neither list is
unknown: kept as written (a unicorn may stand in some room; the policy's search reports it not found), unless
its ending marks an abstract noun ("-tion", "-ness", "-ity"...).
"""

from __future__ import annotations

# The perception vocabulary: every word of query.CATALOG, query.SYNONYMS (both sides) and query.FAMILIES.
PERCEPTION_WORDS = frozenset({
    "red", "cup", "purple", "coke", "can", "soda", "tissue", "box", "green", "bottle", "apple", "orange", "banana",
    "cracker", "cardboard", "small", "large", "wrench", "screwdriver", "hammer", "table", "round", "wooden",
    "shelf", "sink", "counter", "coffee", "machine", "floor", "coca", "cola", "mug", "glass", "tin", "carton",
    "crackers", "tissues", "kleenex", "desk", "bookshelf", "shelves", "worktop", "countertop", "basin", "wood",
    "biscuit", "biscuits", "bin", "snack", "fruit", "food", "tool", "drink", "beverage",
})

PHYSICAL = PERCEPTION_WORDS | frozenset({
    # kitchen and household things
    "bowl", "plate", "dish", "spoon", "fork", "knife", "pan", "pot", "kettle", "jar", "jug", "pitcher", "tray",
    "napkin", "towel", "sponge", "lid", "cap", "straw", "teapot", "thermos", "flask", "tumbler", "canister",
    "container", "package", "packet", "parcel", "bag", "basket", "bucket", "crate", "case", "pouch", "tube",
    "book", "notebook", "pen", "pencil", "marker", "paper", "magazine", "envelope", "letter", "card", "phone",
    "remote", "controller", "key", "keys", "wallet", "purse", "watch", "glasses", "sunglasses", "charger",
    "cable", "battery", "lamp", "candle", "vase", "plant", "pillow", "cushion", "blanket", "toy", "ball", "doll",
    "block", "brick", "cube", "figure", "figurine", "unicorn", "teddy", "bear", "sock", "shoe", "hat", "glove",
    "shirt", "scarf", "umbrella", "clock", "radio", "speaker", "camera", "laptop", "mouse", "keyboard", "tablet",
    "soap", "shampoo", "toothbrush", "toothpaste", "comb", "brush", "mirror", "roll", "tape", "glue", "stapler",
    "ruler", "scissors", "pliers", "drill", "saw", "nail", "screw", "bolt", "nut", "spanner", "mallet", "chisel",
    "file", "level", "clamp", "toolbox", "flashlight", "torch",
    # food and drink
    "lemon", "lime", "pear", "peach", "plum", "grape", "grapes", "berry", "strawberry", "melon", "mango", "kiwi",
    "avocado", "tomato", "potato", "carrot", "onion", "cucumber", "pepper", "egg", "bread", "loaf", "bun",
    "sandwich", "cookie", "chips", "crisps", "candy", "chocolate", "bar", "granola", "cereal", "cheese", "yogurt",
    "milk", "juice", "water", "coffee", "tea", "beer", "wine", "snacks", "drinks", "tools", "fruits",
    # furniture and structure (surfaces and landmarks)
    "chair", "stool", "bench", "sofa", "couch", "bed", "cabinet", "cupboard", "drawer", "dresser", "fridge",
    "refrigerator", "oven", "stove", "microwave", "dishwasher", "stand", "rack", "nightstand", "ledge",
    "island", "cart", "trolley", "door", "window", "wall", "corner", "ceiling", "doorway", "tv", "television",
    "dispenser", "trash", "equipment", "instrument", "document", "ornament", "lotion", "object", "item", "thing",
    "stuff",
})
"""Nouns that name a physical thing (or the perception vocabulary's words): a candidate with such a head is an
object whatever else the command says."""

NOT_OBJECTS = frozenset({
    # time, manner, occasion
    "time", "moment", "minute", "second", "hour", "while", "day", "pace", "speed", "hurry", "rush", "care",
    "caution", "convenience", "leisure", "judgement", "judgment", "discretion", "pause", "delay", "wait",
    "favour", "favor", "sake", "go", "way", "chance", "opportunity", "occasion", "point", "turn", "end", "start",
    "beginning", "rest", "break", "nap", "sleep", "breath", "breather", "look", "glance", "peek",
    "step", "walk", "trip", "flight", "ride", "seat", "stand", "hold", "grip",
    # amounts and units
    "bit", "little", "lot", "bunch", "metre", "meter", "metres", "meters", "m", "cm", "centimetre", "centimeter",
    "millimetre", "degree", "degrees", "foot", "feet", "inch", "inches", "yard", "notch", "increment", "amount",
    "distance", "height", "altitude", "position", "direction", "angle", "side", "slightly",
    # abstract things, activities, talk
    "answer", "solution", "idea", "guess", "initiative", "lead", "hint", "clue", "advice", "help", "job", "task",
    "mission", "question", "problem", "reason", "meaning", "life", "fun", "joy", "luck", "peace", "word", "words",
    "song", "joke", "story", "picture", "photo", "selfie", "note", "notes", "weather", "news", "truth",
    "decision", "action", "plan", "interest", "courage", "energy", "balance", "attention", "risk", "charge",
    "control", "responsibility", "credit", "blame", "advantage", "place", "part", "shape", "form", "order",
    "room", "area", "house", "kitchen", "space", "surroundings", "world", "air", "sky", "ground", "bearings",
    "tidiness", "safety", "gripper", "arm", "claw", "view", "sight", "mind", "heart",
})
"""Nouns no room holds as a thing to pick up (or that a command uses for something else: "with your gripper",
"search the room"): never the target."""

_ABSTRACT_ENDINGS = ("tion", "sion", "ness", "ment", "ity", "ance", "ence", "ism", "ship", "hood", "dom", "ology")
"""Endings of abstract nouns ("a solution", "the happiness"): such an unknown noun is not an object."""


def object_noun(head: str) -> bool | None:
    """Whether `head` (a singular noun) names a physical thing: True (known), False (known not to, or an
    abstract ending), None (unknown: kept as written)."""
    head = head.strip().lower()
    if head in PHYSICAL:
        return True
    if head in NOT_OBJECTS:
        return False
    if len(head) > 5 and head.endswith(_ABSTRACT_ENDINGS):
        return False
    return None
