"""The rules baseline's command reader: a natural-language command in, a `Plan` out (or a refusal with its reason).

Works from words only (it never reads the simulator or perception at run time): it knows task verbs, the
prepositions that name a destination, polite and indirect wrappers, relative clauses that locate an object,
counts and amounts of motion, conditionals, distractors named in a negation, size comparisons, categories,
and a few compound nouns; passive, causative and verb-less forms ("red cup to the table": read as pick and
place, `Plan.note` says so). A noun no room holds ("your time", "a bit", "the answer") is never the target
(rules_lexicon.py). Objects it does not know are kept as written ("pick up the unicorn" targets a
unicorn); the policy matches them against perception's detections. A command with no object, no motion and
no task verb ("sing me a song") is not understood: `Plan.understood` is False and `Plan.reason` says why.

Motion amounts use the executor's default step sizes (45 deg yaw, 0.5 m horizontal, 0.3 m vertical):
"turn right 90 degrees" is two yaw_right steps, "move forward one metre" two forward steps.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from services.reasoner.backends.rules_lexicon import object_noun
from shared import skills as S  # noqa: N812

YAW_STEP_DEG = 45.0
HORIZONTAL_STEP_M = 0.5
VERTICAL_STEP_M = 0.3
MAX_REPEAT = 10  # a count above this is clipped (a typo must not fly the vehicle across the room)
APPROACH = "approach:"  # motion token: fly to the named thing, as many steps as it takes

SNACKS = ("apple", "banana", "orange", "cracker", "chips", "cookie", "granola", "candy", "snack", "chocolate",
          "biscuit", "pear")
CATEGORY_WORDS: dict[str, tuple[str, ...]] = {
    "snack": SNACKS,
    "tool": ("hammer", "screwdriver", "wrench", "pliers", "drill", "scissors", "saw", "tool"),
    "fruit": ("apple", "banana", "orange", "pear", "lemon", "fruit"),
    "drink": ("can", "bottle", "soda", "coke", "juice", "cup", "drink"),
}
# Phrases that name a category rather than an object, rewritten to the category's word before reading.
_CATEGORY_PHRASES = (
    (r"\b(?:something|anything|stuff|some ?thing) (?:to eat|edible|to snack on|tasty|to munch on)\b", "snack"),
    (r"\b(?:some )?(?:food|snacks?|a bite to eat|something i can eat)\b", "snack"),
    (r"\b(?:something|anything) (?:to drink|drinkable)\b|\bbeverages?\b|\bdrinks\b", "drink"),
    (r"\b(?:a piece of fruit|some fruit|fruits)\b", "fruit"),
    (r"\b(?:something|anything) (?:to (?:fix|repair|build) (?:things|stuff|it)( with)?|i can fix things with)\b|"
     r"\btools\b",
     "tool"),
)
SIZE_WORDS = {"larger": {"large", "big", "larger", "bigger", "huge"}, "smaller": {"small", "little", "smaller", "tiny"}}
_LARGER = ("larger", "largest", "bigger", "biggest", "big", "large", "huge", "hugest", "greater", "greatest",
           "bulkier", "bulkiest", "heftier")
_SMALLER = ("smaller", "smallest", "small", "tiny", "tinier", "tiniest", "little", "littler", "littlest", "lesser",
            "compact")
_GENERIC = {"one", "object", "thing", "item", "of", "them", "two", "three", "both", "pair"}

# Verbs, by what they ask for. Multi-word ones first where it matters.
PICK_VERBS = ("pick up", "pick out", "pick", "grab", "get", "take", "fetch", "collect", "snag", "lift", "retrieve",
              "obtain", "seize", "grasp", "nab", "secure", "procure", "acquire", "bring", "carry", "hand", "pass",
              "give", "deliver", "gather", "scoop up", "hold", "pluck", "hoist", "snatch", "grip", "clutch", "haul",
              "lug", "tote", "ferry", "convey", "shuttle", "take hold of", "get hold of", "grab hold of")
FIND_VERBS = ("find", "locate", "look for", "search for", "seek", "hunt for", "hunt down", "track down", "spot")
PLACE_VERBS = ("put", "place", "set", "drop", "deposit", "leave", "lay", "rest", "position", "stick", "stash", "stow",
               "plop", "pop", "park", "transfer", "relocate", "move", "carry", "take", "bring", "deliver", "return",
               "unload", "shift", "dump", "toss", "plonk", "haul", "lug", "tote", "ferry", "convey", "shuttle")
TASK_VERBS = tuple(dict.fromkeys(PICK_VERBS + FIND_VERBS + PLACE_VERBS))
# Verbs after which a plain "on/in/at" is where the object is, not where it goes ("take the cup on the table").
_CARRY_VERBS = {"bring", "carry", "take", "deliver", "get", "fetch", "grab", "pick up", "pick", "collect", "snag",
                "lift", "retrieve", "hand", "pass", "give", "obtain", "return", "gather"}
_DOUBLED = {"grab": "grabbing", "drop": "dropping", "get": "getting", "put": "putting", "set": "setting",
            "snag": "snagging", "nab": "nabbing", "plop": "plopping", "pop": "popping", "stop": "stopping",
            "step": "stepping", "shift": "shifting", "transfer": "transferring"}
_IRREGULAR = {"transferred": "transfer", "taken": "take", "carried": "carry", "laid": "lay", "delivered": "deliver",
              "brought": "bring", "took": "take", "got": "get", "gotten": "get", "picked": "pick", "placed": "place",
              "grabbed": "grab", "fetched": "fetch", "moved": "move", "dropped": "drop"}

# Determiners and fillers before a noun phrase; words that end one.
_DET = {"the", "a", "an", "some", "that", "this", "those", "these", "my", "your", "our", "any", "me", "us", "one",
        "of", "single", "whichever", "whatever", "either", "each", "another", "other"}
_NP_STOP = {"on", "onto", "in", "into", "inside", "to", "from", "at", "by", "near", "next", "beside", "behind",
            "under", "below", "beneath", "over", "across", "off", "with", "toward", "towards", "for", "of", "that",
            "which", "who", "whose", "sitting", "lying", "resting", "located", "standing", "placed", "kept", "found",
            "seen", "and", "then", "but", "or", "not", "if", "so", "up", "down", "when", "once", "after", "before",
            "while", "there", "here", "now", "quickly", "carefully", "gently", "again", "too", "as", "where",
            "without", "instead", "rather", "except", "is", "are", "was", "somewhere", "around", "it", "them",
            "out", "back", "away", "atop", "upon", "against", "between", "among", "please", "right", "left",
            "immediately", "first", "afterwards", "otherwise", "else", "unless", "than", "nearby", "close", "along",
            "to-", "asap", "thanks", "thank", "real", "very", "anywhere", "everywhere", "within", "above",
            "all", "only", "just", "currently", "you", "i", "we", "he", "she", "they", "forward", "forwards",
            "backward", "backwards", "ahead", "upward", "upwards", "downward", "downwards", "sideways", "clockwise",
            "slightly", "a bit"}
_VERB_STOP = {"bring", "grab", "pick", "take", "get", "fetch", "put", "place", "find", "locate", "carry", "move",
              "deliver", "collect", "retrieve", "lift", "drop", "snag", "seize", "grasp", "hand", "give", "deposit",
              "set", "leave", "turn", "fly", "go", "rotate", "approach", "is", "are", "be"}
_PRONOUNS = {"it", "them", "that", "this", "one", "those", "these", "the object", "the item", "the thing"}
_NOT_DESTINATION = {"me", "here", "us", "over here", "my hand", "my hands", "the operator", "you", "back here"}
_COMPOUNDS = ((r"\bkitchen counter(?:top)?\b|\bcounter ?tops?\b|\bworktops?\b", "counter"),
              (r"\bkitchen sink\b", "sink"), (r"\bbook ?(?:shelf|shelves|case)\b|\bshelves\b", "shelf"),
              (r"\bcoffee maker\b|\bespresso machine\b", "coffee machine"),
              (r"\bbox of crackers\b|\bcracker box\b|\bcrackers box\b", "cracker box"),
              (r"\bbox of tissues\b|\btissues box\b", "tissue box"), (r"\bcan of coke\b", "coke can"),
              (r"\bcan of soda\b", "soda can"), (r"\bbottle of water\b|\bwater bottle\b", "bottle"))

# Destination prepositions: strong ones name a destination after any verb; weak ones only after a put-verb.
_STRONG_PREP = (r"(?:over |across |back |down |up |right )?(?:onto|into|on to|in to|to|toward|towards)|on top of|"
                r"(?:over |across )?to the top of|atop|upon|inside of|over onto|back onto|back into")
_WEAK_PREP = (r"(?:back |down |up )?(?:on|in|inside|at|next to|beside|near|by|in front of|on the top of|under|"
              r"underneath)")
_LOCATOR_MARK = (r"(?:(?:that|which|who)\s+(?:is|are|was|were|'s|sits?|lies?|rests?|stands?|can be found|you (?:see|"
                 r"can see|saw|will find|find))\s+|that's\s+)?(?:(?:sitting|lying|resting|located|standing|placed|"
                 r"kept|found|left|seen|waiting)\s+)?")
_FROM = r"(?:from|off|off of|out of|away from)"
_AT = r"(?:on|in|inside|at|by|near|next to|beside|behind|under|in front of|on top of|over by|over on|over at|close to)"


@dataclass
class Plan:
    """What the command asks for, read from its words."""

    motions: list[str] = field(default_factory=list)
    target: str | None = None
    choices: list[str] = field(default_factory=list)
    selector: str | None = None  # "larger" or "smaller"
    group: str | None = None  # "box" in "of the two boxes"
    category: str | None = None  # "snack" in "bring me a snack"
    excluded: list[str] = field(default_factory=list)
    destination: str | None = None
    understood: bool = True
    reason: str = ""
    """Why the command is refused (when not understood)."""
    note: str = ""
    """What the reader made of a command it was unsure of ("no task verb: read as ..."), for the task's first
    step to say instead of refusing."""

    def as_record(self) -> dict:
        """The fields of a phrasing-set line (tests/reasoner/data/phrasings_dev.jsonl)."""
        return {"target": self.target, "destination": self.destination, "motions": list(self.motions),
                "selector": self.selector, "group": self.group, "category": self.category,
                "excluded": list(self.excluded), "choices": list(self.choices), "understood": self.understood}


def singular(word: str) -> str:
    """'boxes' -> 'box', 'berries' -> 'berry', 'cups' -> 'cup' (the last word of a phrase only)."""
    word = word.strip()
    if not word:
        return word
    head, _, last = word.rpartition(" ")
    if last in ("glasses", "scissors", "pliers", "chips", "tongs", "this", "is", "bus", "lens", "gas", "news"):
        out = last
    elif last.endswith(("xes", "ches", "shes", "sses")):
        out = last[:-2]
    elif last.endswith("ies") and len(last) > 4:
        out = last[:-3] + "y"
    elif last.endswith("s") and not last.endswith(("ss", "us", "is")) and len(last) > 2:
        out = last[:-1]
    else:
        out = last
    return f"{head} {out}" if head else out


def _verb_forms() -> dict[str, str]:
    """Inflected form -> base verb ("grabbing" -> "grab", "puts" -> "put")."""
    out = dict(_IRREGULAR)
    words = {w for v in TASK_VERBS for w in v.split()[:1]} | {"turn", "rotate", "move", "fly", "go", "head", "spin",
                                                              "approach", "search", "look", "hunt", "track"}
    for v in words:
        ing = _DOUBLED.get(v) or (v[:-1] + "ing" if v.endswith("e") and not v.endswith("ee") else v + "ing")
        out[ing] = v
        out[v + ("es" if v.endswith(("sh", "ch", "ss", "x")) else "s")] = v
    return out


_FORMS = _verb_forms()
_POLITE = (
    r"\b(?:hey|hi|hello|ok|okay|yo)\b,?\s+(?:drone|robot|buddy|there|copter)\b,?",
    r"\b(?:drone|robot|copter)\s*,",
    r"\bi(?: would|'d|d)? (?:like|love|want|need|wish)(?: for)? (?:you|u) to\b",
    r"\bi (?:would|'d) (?:really )?appreciate (?:it )?if you (?:could|would|can)\b",
    r"\bit (?:would|'d) be (?:great|nice|helpful|lovely|awesome|perfect) if you (?:could|would|can)\b",
    r"\b(?:do|would you do) me a favou?r and\b",
    r"\b(?:could|can|would|will) (?:you|u)(?: please)?(?: kindly)?(?: (?:mind|be so kind as to|be able to|try to|"
    r"possibly|just|maybe|go ahead and))*\b",
    r"\bhow about you\b", r"\bwhy don't you\b", r"\blet's\b", r"\blet us\b", r"\byour (?:task|job|mission) is to\b",
    r"\byou (?:should|need to|must|have to|can|could)\b", r"\bplease\b", r"\bkindly\b", r"\bgo ahead and\b",
    r"\bbe a dear and\b", r"\btry (?:to|and)\b", r"\bif you (?:can|could|would|don't mind|do not mind|please)\b",
    r"\bif possible\b", r"\bwhen you (?:get a chance|can)\b", r"\bthanks?(?: you)?(?: so much)?\b", r"\bfor me\b",
    r"\bwould be great\b", r"\bi'm asking you to\b", r"\bi am asking you to\b", r"\bmind\b", r"\bjust\b",
    r"\bnow\b", r"\bpls\b", r"\bplz\b", r"\bthx\b", r"\bquickly\b", r"\bcarefully\b", r"\bgently\b",
    r"\bright away\b", r"\basap\b",
)
_WANTS = (r"\b(?:i(?: would|'d|d)? (?:like|love|want|need|wish for)|i could (?:use|do with)|i will have|"
           r"i'?m (?:craving|looking for)|"
          r"i am (?:craving|looking for)|can i (?:have|get)|could i (?:have|get)|may i (?:have|get)|let me have|"
          r"give me|hand me|pass me|get me|grab me|fetch me|bring me)\b")
_CONTRACTIONS = (("i'd", "i would"), ("i'll", "i will"), ("we'd", "we would"), ("it'd", "it would"),
                 ("isn't", "is not"), ("don't", "do not"), ("doesn't", "does not"), ("isn't", "is not"),
                 ("aren't", "are not"),
                 ("can't", "cannot"), ("won't", "will not"), ("there's", "there is"), ("it's", "it is"),
                 ("that's", "that is"), ("what's", "what is"), ("where's", "where is"), ("i'm", "i am"),
                 ("you're", "you are"), ("you'll", "you will"), ("shouldn't", "should not"))


def normalize(command: str) -> str:
    """Lower case, straight quotes, contractions expanded, politeness removed, verbs in their base form."""
    c = " " + " ".join(command.lower().replace("’", "'").replace("‘", "'").replace("“", '"').replace("”", '"')
                       .split()) + " "
    for a, b in _CONTRACTIONS:
        c = c.replace(a, b)
    c = re.sub(r"\bwhich ever\b", "whichever", c)
    # before the politeness words go ("mind", "if you can"): phrases that carry meaning with them
    c = re.sub(r"\bnever mind\b", " ignore ", c)
    c = re.sub(r"\bsee if you can (?=find|spot|locate|see)\b", " ", c)
    c = re.sub(r"^\s*(?:so\s*,?\s*)?where (?:is|are)\b|\bcan you tell me where (?:is|are)\b", " find ", c)
    c = re.sub(r"\bhave a look (?:around )?for\b", " find ", c)
    c = re.sub(r"(?:^|(?<=[.;!?]))\s*(?:do|can|could) you (?:see|spot)\b|(?:^|(?<=[.;!?]))\s*(?:is|are) there\b",
               " find ", c)
    c = re.sub(r"\s*(?:->|=>|→)\s*", " to ", c)  # "red cup -> table"
    # amounts written out, so one pattern reads them ("ninety degrees", "half a metre")
    c = re.sub(r"\b(?:a|one) hundred (?:and )?eighty\b", "180", c)
    c = re.sub(r"\bthree hundred (?:and )?sixty\b", "360", c)
    c = re.sub(r"\bninety\b", "90", c)
    c = re.sub(r"\bforty[- ]five\b", "45", c)
    c = re.sub(r"\bhalf (?:a |of a )?(met(?:re|er)|m)\b", r"0.5 \1", c)
    c = re.sub(r"\bquarter (?:of )?(?:a )?(met(?:re|er))\b", r"0.25 \1", c)
    c = re.sub(r"\s(?:--+|—|–)\s", " ; ", c)
    c = re.sub(r"\bi(?: would)? (?:like|want|love|need) (?P<x>(?:the |a |an |my )?[a-z][a-z \-]*?) (?P<p>on top of|"
               r"onto|into|on|in|"
               r"inside) (?=the |a |my )", r"put \g<x> \g<p> ", c)
    words = [_FORMS.get(w, w) for w in re.findall(r"\d+\.\d+|[a-z0-9'\-]+|[^\sa-z0-9'\-]", c)
             if w not in ("really", "actually", "maybe", "perhaps", "kindly", "um", "uh")]
    c = " " + " ".join(words) + " "
    c = re.sub(r"\s+([,.;:!?])", r"\1", c)
    for p in _POLITE:
        c = re.sub(p, " ", c)
    c = re.sub(_WANTS, " bring me ", c)
    c = re.sub(r"\bpick (?:it|them) up\b", "pick up it", c)
    c = re.sub(r"\b(?:search|scan|explore|check|sweep|comb|look)(?: (?:through|around|in|all over|across))? "
               r"(?:the |this |your )?(?:room|area|house|place|kitchen|space|surroundings|everywhere|around)"
               r"(?:\s+(?:and|to))?(?:\s+(?:for|until you find))?\b", " find ", c)
    c = re.sub(r"\b(?:look|search|hunt|scan)(?: around)? for\b|\blook around for\b|\bgo find\b|\bsee if you can find\b",
               " find ", c)
    c = re.sub(r"\bfind(?:\s+(?:and\s+|to\s+)?find)+\b", "find", c)
    c = re.sub(r"\bgo (?:and )?(get|grab|fetch|pick up|collect|retrieve|find|bring)\b", r" \1 ", c)
    c = re.sub(r"\b(?:set|put|lay|place|drop|plop) (it|them|that|this)? ?down\b", r" put \1 ", c)
    c = re.sub(r"\bdrop (it|them|that|this)? ?off\b", r" put \1 ", c)
    for pat, rep in _COMPOUNDS:  # before the passive forms read a name ("the can of coke can be put ...")
        c = re.sub(pat, rep, c)
    # causatives: "have the cup put on the table", "make the cup go to the table", "get the cup moved to ..."
    c = re.sub(r"^\s*(?:make|have|get) (?:the |a |an |my )?(?P<x>[a-z](?:(?!\b(?:and|then|or|but|in|on|at|to|into|"
               r"onto|from|with|for|by)\b)[a-z \-])*?) "
               r"(?:go|end up|put|place|move|set|bring|take|carry|transfer|drop|lay|deposit)\b", r"put the \g<x>", c)
    # "can" is a modal here unless it ends a can's name ("the coke can should go ..."); "the coke can be put on
    # the shelf" names the can and the modal at once
    c = re.sub(r"^(\s*(?:the |a |an |my )?[a-z \-]*?\b(?:coke|soda|cola|beer|paint|trash)) can (be|go)\b",
               r"\1 can can \2", c)
    c = re.sub(r"^\s*(?:the |a |an |my )?(?P<x>[a-z][a-z \-]*?) (?:(?:needs|has|should|must|ought|is|are|has got|"
               r"will|would|could|(?<!\bcoke )(?<!\bsoda )(?<!\bcola )(?<!\bbeer )(?<!\bpaint )(?<!\btrash )can|"
               r"may|might)(?: really)? (?:to )?(?:go|be (?:put|place|placed|move|moved|set|"
               r"bring|brought|take|taken|return|returned|carry|carried|lay|laid|leave|left|drop|dropped|transfer|"
               r"transferred|stick|stuck|deposit|deposited|rest|rested|shift|shifted)|end up|get put|live|sit|stay)|"
               r"belongs?|goes|(?:is|are) supposed to (?:be|go)|(?:would|will) (?:be|look) better|should (?:be|stay|"
               r"sit)|must be|needs to be)\b", r"put the \g<x>", c)
    for pat, rep in _CATEGORY_PHRASES:
        c = re.sub(pat, f" {rep} ", c)
    return " ".join(c.split())


# --------------------------------------------------------------------------- noun phrases


def noun_phrase(text: str) -> str:
    """The object's words at the start of `text`: determiners skipped, up to the first word that ends it."""
    words = re.findall(r"\d+\.\d+|[a-z0-9\-]+|[^\sa-z0-9\-]", text.strip())
    out: list[str] = []
    i = 0
    while i < len(words) and not out and (words[i] in _DET or words[i] in ("up", "out", "down", "off")):
        if words[i] == "one" and (i + 1 >= len(words) or words[i + 1] in _NP_STOP or not words[i + 1].isalpha()):
            return "one"
        i += 1
    for w in words[i:]:
        if out and _adverb(w):
            break
        if not re.fullmatch(r"[a-z0-9][a-z0-9\-]*", w) or w in _NP_STOP or (out and w in _DET and w != "one") \
                or (out and w in _VERB_STOP):
            break
        out.append(w)
        if len(out) >= 4:
            break
    return " ".join(out)


def _adverb(word: str) -> bool:
    """"slowly", "safely": a manner adverb ends a noun phrase ("grab the cup slowly")."""
    return len(word) >= 6 and word.endswith("ly") and object_noun(word) is not True


def _clean(np_: str) -> str | None:
    np_ = singular(np_.strip())
    return np_ or None


# --------------------------------------------------------------------------- special constructions

_OBJ = r"((?:(?!\b(?:otherwise|else|if|then|and|but|or|not|please)\b)[a-z0-9\- ])+?)"
_ELSE = (r"(?:[,;.]\s*|\s+)(?:and\s+|but\s+|or\s+)?(?:otherwise|or else|else|if not|failing that|if (?:there is|"
         r"you see|you find|"
         r"you spot) (?:none|nothing|no [a-z]+)|if (?:there is not|there are not)(?: (?:one|any))?|"
         r"if you (?:cannot|do not|"
         r"can not|did not) (?:see|find|spot)(?: (?:one|it|any|them))?|if none|if it is not there|if not there|"
         r"in case there is none)\b,?")
_IF_IS = (r"\b(?:if|in case|should|when|provided)\s+(?:there is\s+)?(?:a|an|the|any|some)\s+"
          r"(?=[a-z\- ]+?\s+(?:is|are|happens|can be|exists|shows up|turns up)\b)")
_IF_SEE = (r"\b(?:if|in case|should|when|whenever|provided)\s+(?:you\s+)?(?:can\s+)?(?:see|find|spot|notice|detect|"
           r"there (?:is|are)|there happens to be|you come across)\s+")


_NEG_FIRST = re.compile(r"^\s*(?:if|in case|should)\s+(?:you\s+)?(?:cannot|can not|do not|did not|could not|"
                        r"fail to)\s+(?:see|find|spot|locate)\s+(?P<a>[a-z][a-z \-]*?)\s*,\s*"
                        r"(?:then\s+)?(?P<b>[^;.]*?)\s*[;.,]?\s*"
                        r"(?:otherwise|or else|else|if you do|if you can)\b,?(?P<rest>.*)$")


def _conditional(c: str, plan: Plan) -> str:
    """"If you see an orange, pick it up; otherwise grab the banana" -> choices [orange, banana]; the rest of the
    command is returned. A conditional without an else branch names the target."""
    neg = _NEG_FIRST.match(c)
    if neg:  # "if you cannot find the apple, take the banana; otherwise take the apple": [apple, banana]
        first, second = noun_phrase(neg.group("a")), noun_phrase(_after_verb(neg.group("b")) or neg.group("b"))
        if first and second and first not in _PRONOUNS and second not in _PRONOUNS:
            plan.choices = [singular(first), singular(second)]
            plan.destination = _branch_destination(neg.group("b")) or _branch_destination(neg.group("rest"))
            return ""
    m = re.search(_ELSE, c)
    head = c[: m.start()] if m else c
    cond = re.search(_IF_SEE + r"(.*)", head) or re.search(_IF_IS + r"(.*)", head)
    if m and cond:
        first = noun_phrase(cond.group(1))
        if first in ("it", "one", ""):  # "grab the orange if you see it, otherwise ..."
            first = noun_phrase(_after_verb(c[: cond.start()]) or "")
        after = c[m.end():]
        cut = re.search(r"[.;!?]|\bthen\b|\band (?:then )?(?:put|place|set|drop|bring|move)\b", after)
        second_text = after[: cut.start()] if cut else after
        second = noun_phrase(_after_verb(second_text) or second_text)
        if first and second and second not in _PRONOUNS:
            plan.choices = [singular(first), singular(second)]
            start = min(cond.start(), _verb_start(c[: cond.start()]))
            plan.destination = _branch_destination(c[start: m.start()]) or _branch_destination(second_text)
            return c[:start] + " " + (after[cut.start():] if cut else "")
    if m and not cond and _after_verb(head):  # "take the orange, or if there is not one, the apple"
        first = noun_phrase(_after_verb(head) or "")
        after = c[m.end():]
        cut = re.search(r"[.;!?]|\bthen\b|\band (?:then )?(?:put|place|set|drop|bring|move)\b", after)
        second_text = after[: cut.start()] if cut else after
        second = noun_phrase(_after_verb(second_text) or second_text)
        if first and second and first not in _PRONOUNS and second not in _PRONOUNS:
            plan.choices = [singular(first), singular(second)]
            return c[: _verb_start(head)] + " " + (after[cut.start():] if cut else "")
    if cond and not m:
        first = noun_phrase(cond.group(1))
        if first and first not in _PRONOUNS:
            end = cond.start(1) + cond.group(1).find(first) + len(first)  # past the object's words
            rest = re.sub(r"\b(it|them|that|one)\b", first, c[end:], count=1)
            return c[: cond.start()] + " " + re.sub(r"^[\s,]*(?:then\s+)?", "", rest)
    return c


def _branch_destination(text: str) -> str | None:
    """The destination a conditional's branch names ("put it on the table", "place the banana in the sink")."""
    for vm in _VERB_RE.finditer(text + " "):
        rest = text[vm.end():]
        pro = re.match(r"\s*(?:it|them|that|this|one)\b", rest)
        np_ = _object_np(rest)
        if pro:
            after = rest[pro.end():]
        elif np_:
            last = np_.split()[-1]
            after = rest[rest.find(last) + len(last):]
        else:
            continue
        verb = vm.group("verb")
        dest = _destination_after(after, verb if verb in PLACE_VERBS else "carry")
        if dest:
            return dest
    return None


def _verb_start(text: str) -> int:
    """Start of the last task verb in `text` (or len(text))."""
    last = len(text)
    for m in re.finditer(r"\b(" + "|".join(re.escape(v) for v in TASK_VERBS) + r")\b", text):
        last = m.start()
    return last if last < len(text) and not re.search(r"[.;]", text[last:]) else len(text)


def _after_verb(text: str) -> str | None:
    """The words after the first task verb of `text`, or None."""
    m = re.search(r"\b(" + "|".join(re.escape(v) for v in TASK_VERBS) + r")\b\s*(?:up\s+|me\s+)?", text)
    return text[m.end():] if m else None


_LIST_END = r"(?=\s*(?:\band\b|\bor\b|\bnor\b|\bthen\b|[,.;:!?]|$))"
_EXCLUDE = (
    r"\b(?:ignore|ignoring|disregard|disregarding|skip|avoid|avoiding|forget about|never mind)\s+(?:the |all |any |"
    r"those |these |every )?(?:other )?" + _OBJ + _LIST_END,
    r"\b(?:do not|never|without) (?:touch|touching|take|taking|grab|grabbing|pick up|picking up|pick|get|move|"
    r"moving|disturb|disturbing|bother with|knock over) (?:the |a |an |any |those |these )?" + _OBJ + _LIST_END,
    r"(?:^\s*|,\s*|\s+)(?:and |but |though |just )?not (?:the |a |an |that |this |any |those )?" + _OBJ +
    r"(?=\s*(?:\band\b|\bor\b|\bnor\b|\bthen\b|[,.;:!?]|$))",
    r"\b(?:rather than|instead of|except(?: for)?|other than|apart from|but not|as opposed to|anything but|"
    r"everything but|anything except|not including|excluding) (?:the |a |an |any )?"
    + _OBJ + _LIST_END,
    r"\bleave (?:the |a |an |any |those |these )?" + _OBJ + r"(?P<more>(?:(?:\s*,\s*(?:and\s+|or\s+)?|\s+(?:and|or)\s+)"
    r"(?:the |a |an |any )?" + _OBJ + r")*)\s+(?:alone|be|where (?:it is|they are)|untouched|in place)",
)
_LEAVE = re.compile(r"\b(?:and |but |then )?leave (?:the |a |an |any |those |these )?(?P<np>[a-z0-9\- ]+?)"
                    r"(?=\s*(?:\band\b|\bthen\b|[,.;:!?]|$))")
# One more item of a list of distractors: "ignore the hammer, the wrench and the drill", "don't touch the cup or
# the can". An item starts with a determiner, so "ignore the tools and pick up the bottle" ends at "tools".
_MORE = r"(?:\s*,\s*(?:and\s+|or\s+)?|\s+(?:and|or|nor)\s+)(?:the|a|an|any|those|these)\s+" + _OBJ + _LIST_END
_MORE_OR = r"\s+(?:or|nor)\s+(?:the|a|an|any)\s+" + _OBJ + _LIST_END  # after "not the X": "or"/"nor" only


def _exclusions(c: str, plan: Plan) -> str:
    """Distractors named in a negation ("not the coke can", "ignore the tools", a list of them) -> plan.excluded."""
    for k, pat in enumerate(_EXCLUDE):
        while True:
            m = re.search(pat, c)
            if not m:
                break
            names = [m.group(1)]
            end = m.end()
            if "more" in m.re.groupindex:  # "leave the X and the Y where they are"
                names += [x for x in re.split(r"\s*,\s*(?:and\s+|or\s+)?|\s+(?:and|or)\s+", m.group("more")) if x]
            else:
                more = _MORE_OR if k == 2 else _MORE
                while (x := re.match(more, c[end:])) is not None:
                    names.append(x.group(1))
                    end += x.end()
            for name in names:
                np_ = noun_phrase(name)
                if np_ and np_ not in _PRONOUNS:
                    plan.excluded.append(singular(np_))
            c = c[: m.start()] + " " + c[end:]
    for m in list(_LEAVE.finditer(c))[::-1]:  # "... and leave the purple cup": a distractor, when nothing follows
        if noun_phrase(m.group("np")) == m.group("np").strip() and m.group("np").strip() not in _PRONOUNS:
            plan.excluded.append(singular(m.group("np").strip()))
            c = c[: m.start()] + " " + c[m.end():]
    return c


def _selector(c: str, plan: Plan) -> None:
    """Size comparisons: the larger/smaller one of a group, resolved later from measured sizes."""
    words = "|".join(_LARGER + _SMALLER)
    m = re.search(r"(?<!\ba )(?<!\bjust a )\b(" + words
                  + r")\b(?! (?:bit|while|further|more|higher|lower|closer)\b)", c)
    if not m:
        return
    plan.selector = "larger" if m.group(1) in _LARGER else "smaller"
    after = c[m.end():]
    candidates = [
        re.search(r"^\s+(?:one )?(?:of|among|between|out of) (?:the |these |those |all )?(?:two |three |four |\d+ |"
                  r"both )?([a-z\- ]+)", after),
        re.search(r"\b(?:of|among|between|out of) (?:the |these |those |all )?(?:two |three |four |\d+ |both )?"
                  r"([a-z\- ]+?)\s*,", c[: m.start()]),
        re.search(r"\b(?:whichever|which|the)\s+([a-z\- ]+?)\s+(?:that )?(?:is|looks|seems|appears)\s+(?:the )?"
                  r"(?:" + words + r")\b", c),
        re.search(r"^\s+([a-z\- ]+)", after),
    ]
    for g in candidates:
        if g is None:
            continue
        np_ = noun_phrase(g.group(1))
        if np_ and np_.split()[-1] not in _GENERIC and np_ not in CATEGORY_WORDS:
            plan.group = singular(np_)
            return
        if np_ in CATEGORY_WORDS:
            plan.group = np_
            return


# --------------------------------------------------------------------------- motions

_DIRS = {"forward": S.FORWARD, "forwards": S.FORWARD, "ahead": S.FORWARD, "straight": S.FORWARD,
         "closer": S.FORWARD, "backward": S.BACKWARD, "backwards": S.BACKWARD, "back": S.BACKWARD,
         "left": S.LEFT, "right": S.RIGHT, "up": S.UP, "higher": S.UP, "upward": S.UP, "upwards": S.UP,
         "down": S.DOWN, "lower": S.DOWN, "downward": S.DOWN, "downwards": S.DOWN, "sideways left": S.LEFT}
_NUM = {"a": 1, "an": 1, "one": 1, "once": 1, "single": 1, "two": 2, "twice": 2, "couple": 2, "pair": 2,
        "three": 3, "thrice": 3, "four": 4, "five": 5, "six": 6, "seven": 7, "eight": 8, "nine": 9, "ten": 10,
        "few": 3, "several": 3, "half": 0.5, "quarter": 0.25}
_COUNT_NAMED = (r"(?:\s+(?:by\s+|for\s+|about\s+|around\s+|roughly\s+|some\s+)?(?:a\s+)?"
          r"(?P<n>\d+(?:\.\d+)?|a|an|one|two|three|four|five|six|seven|eight|nine|ten|couple(?: of)?|few|several|"
          r"half|quarter|once|twice|thrice)"
          r"(?:\s+(?P<unit>times?|steps?|meters?|metres?|m|centimeters?|centimetres?|cm|feet|foot|ft|degrees?|deg|"
          r"turns?|rotations?|notches?|increments?|moves?))?)")
_COUNT = _COUNT_NAMED.replace("?P<n>", "?:").replace("?P<unit>", "?:")
_TURN = re.compile(r"\b(?:turn|rotate|yaw|spin|pivot|swivel|face|veer)(?:\s+(?:yourself|your ?self|the drone|around|"
                   r"round))?(?P<pre>" + _COUNT + r")?\s+(?:to (?:the |your )?)?(?P<dir>left|right|"
                   r"counter-?clockwise|anti-?clockwise|clockwise)(?P<post>" + _COUNT + r")?")
_TURN_AROUND = re.compile(r"\b(?:turn|spin|rotate|swing)\s+(?:yourself\s+)?(?:all the way\s+)?around\b"
                          r"(?!\s+(?:to (?:the |your )?)?(?:left|right|clockwise|counter|anti))(?P<post>" + _COUNT
                          + r")?|"
                          r"\bturn back\b|\babout[- ]face\b|\b(?:do|make) a u-?turn\b")
_TURN_BY = re.compile(r"\b(?:turn|rotate|yaw|spin|pivot|swivel)(?:\s+(?:yourself|around|round))?(?P<post>"
                      r"(?:\s+(?:by\s+|about\s+)?(?:\d+|ninety|forty-five|a hundred and eighty)\s+(?:degrees?|deg)\b|"
                      r"\s+(?:a\s+)?(?:quarter|half)(?:\s+(?:a\s+)?(?:turn|circle|rotation))?\b))"
                      r"(?!\s+(?:to (?:the |your )?)?(?:left|right|clockwise|counter|anti))")
_FULL_TURN = re.compile(r"\b(?:do|make|perform|spin|rotate|turn)\s+(?:a\s+)?(?:full|complete|whole)\s+"
                        r"(?:turn|circle|rotation|360|spin)\b|\b(?:spin|rotate|turn)\s+(?:a\s+)?(?:full\s+)?360\b")
_MOVE = re.compile(r"\b(?:move|go|fly|step|head|drift|shift|slide|strafe|glide|travel|float|hover|inch|nudge|"
                   r"scoot|sidestep|climb|rise|ascend|descend|drop|lower|raise|come|back up|advance|proceed|"
                   r"continue|get|reverse|retreat|back off|push)(?:\s+(?:yourself|the drone|over|on))?"
                   r"(?P<pre>" + _COUNT + r")?\s*(?:to (?:the |your )?)?(?P<dir>forwards?|ahead|straight|closer|"
                   r"backwards?|back|left|right|up|higher|upwards?|down|lower|downwards?)\b(?P<post>" + _COUNT
                   + r")?")
_BARE = re.compile(r"\b(?P<verb>advance|ascend|climb|rise|descend|reverse|retreat|back up|back off|go higher|"
                   r"go lower|gain altitude|lose altitude|lower yourself|raise yourself)\b(?P<post>" + _COUNT + r")?")
_LONE_DIR = re.compile(r"(?:then\s+|and\s+)?(?P<dir>forwards?|ahead|backwards?|back|left|right|up|down|higher|lower)\b"
                       r"(?P<post>" + _COUNT + r")?\s*$")
_BARE_DIR = {"advance": S.FORWARD, "ascend": S.UP, "climb": S.UP, "rise": S.UP, "go higher": S.UP,
             "gain altitude": S.UP, "raise yourself": S.UP, "descend": S.DOWN, "go lower": S.DOWN,
             "lose altitude": S.DOWN, "lower yourself": S.DOWN, "reverse": S.BACKWARD, "retreat": S.BACKWARD,
             "back up": S.BACKWARD, "back off": S.BACKWARD}
_GOTO = re.compile(r"\b(?:approach|go|fly|head|move|travel|navigate|proceed|get|come|hover|make your way|"
                   r"go over|fly over|head over|move over)\s*(?:over\s+|on\s+|straight\s+|right\s+)?"
                   r"(?:to|toward|towards|up to|near|close to|next to|over to|in front of|beside)?\s*"
                   r"(?:the|a|an|that|this)\s+(?P<what>[a-z][a-z \-]*)")
_STEP_COUNT = re.compile(r"(?<![\d.])\b(?P<n>\d+(?:\.\d+)?|a|an|"
                         r"one|two|three|four|five|six|couple(?: of)?|few)\s+(?P<unit>steps?|meters?|"
                         r"metres?|m)\s+(?:to (?:the |your )?)?(?P<dir>forwards?|ahead|backwards?|back|left|"
                         r"right|up|down)\b")


_NUM_WORDS = set(_NUM) - {"a", "an", "one", "single"} | {str(i) for i in range(100)}


def _number(word: str | None) -> float | None:
    if not word:
        return None
    word = word.replace(" of", "").strip()
    try:
        return float(word)
    except ValueError:
        return _NUM.get(word)


def _amount(m: re.Match, skill: str, keys: tuple[str, ...] = ("pre", "post")) -> int:
    """Steps of `skill` a count/amount asks for: N times, N degrees (45 per step), N metres (step size)."""
    for key in keys:
        text = m.group(key) if key in m.re.groupindex else None
        if not text:
            continue
        cm = re.search(_COUNT_NAMED, " " + text)
        if not cm:
            continue
        n, unit = _number(cm.group("n")), (cm.group("unit") or "times")
        if n is None:
            continue
        if unit.startswith(("deg", "notch")):
            return _clip(round(n / YAW_STEP_DEG))
        if unit.startswith(("turn", "rotation")) and skill in (S.YAW_LEFT, S.YAW_RIGHT):
            return _clip(round(n * 360 / YAW_STEP_DEG))
        if unit.startswith(("met", "m", "cm", "cent", "f")) and unit not in ("moves", "move"):
            metres = n / 100 if unit.startswith(("cm", "cent")) else n * 0.3048 if unit.startswith("f") else n
            step = VERTICAL_STEP_M if skill in (S.UP, S.DOWN) else HORIZONTAL_STEP_M
            return _clip(round(metres / step))
        return _clip(round(n))
    return 1


def _clip(n: int) -> int:
    return max(1, min(int(n), MAX_REPEAT))


def _turn_skill(direction: str) -> str:
    return S.YAW_RIGHT if direction in ("right", "clockwise") else S.YAW_LEFT


def motions(clause: str) -> list[str]:
    """The motion skills a clause spells out, in order, repeated for counts and amounts."""
    found: list[tuple[int, list[str]]] = []
    taken: list[tuple[int, int]] = []

    def add(m: re.Match, skills: list[str]) -> None:
        if any(a < m.end() and m.start() < b for a, b in taken):
            return
        taken.append((m.start(), m.end()))
        found.append((m.start(), skills))

    for m in _FULL_TURN.finditer(clause):
        add(m, [S.YAW_LEFT] * int(360 / YAW_STEP_DEG))
    for m in _TURN_AROUND.finditer(clause):
        add(m, [S.YAW_LEFT] * _clip(int(180 / YAW_STEP_DEG) * _amount(m, S.YAW_LEFT, ("post",))))
    for m in _TURN_BY.finditer(clause):
        text = m.group("post").replace("ninety", "90").replace("forty-five", "45").replace("a hundred and eighty",
                                                                                         "180")
        digits = re.search(r"\d+", text)
        deg = 90.0 if "quarter" in text else 180.0 if "half" in text else float(digits.group() if digits else 90)
        add(m, [S.YAW_LEFT] * _clip(round(deg / YAW_STEP_DEG)))
    for m in _TURN.finditer(clause):
        skill = _turn_skill(m.group("dir"))
        add(m, [skill] * _amount(m, skill))
    for m in _STEP_COUNT.finditer(clause):
        skill = _DIRS[m.group("dir")]
        n = _number(m.group("n")) or 1
        unit = m.group("unit")
        step = 1.0 if unit.startswith("step") else VERTICAL_STEP_M if skill in (S.UP, S.DOWN) else HORIZONTAL_STEP_M
        add(m, [skill] * _clip(round(n / step)))
    for m in _MOVE.finditer(clause):
        skill = _DIRS[m.group("dir")]
        add(m, [skill] * _amount(m, skill))
    for m in _BARE.finditer(clause):
        skill = _BARE_DIR[m.group("verb")]
        add(m, [skill] * _amount(m, skill, ("post",)))
    lone = _LONE_DIR.match(clause)
    if lone and not found:  # "... and forward twice": the verb was in the clause before
        skill = _DIRS[lone.group("dir")]
        add(lone, [skill] * _amount(lone, skill, ("post",)))
    for m in _GOTO.finditer(clause):
        what = noun_phrase(m.group("what"))
        if what and what not in _DIRS and what.split()[0] not in _DIRS and not not_an_object(what):
            add(m, [APPROACH + singular(what)])
    return [s for _pos, skills in sorted(found, key=lambda f: f[0]) for s in skills]


def _named_skills(clause: str, skills: list[str] | tuple[str, ...]) -> list[tuple[int, str]]:
    """Registered skills the clause names outright ("descend to inspect" -> descend_to_inspect), with their
    position: a skill added to the library is usable in an explicit sequence without touching this file."""
    found = []
    skip = set(S.MOTION_PRIMITIVES) | {S.OBJ_LOCALIZATION, S.GRASP, S.PLACEMENT_LOCALIZATION, S.PLACE, S.DONE}
    for name in skills:
        if name in skip:
            continue
        for phrase in {name, name.replace("_", " ")}:
            for m in re.finditer(r"\b" + re.escape(phrase) + r"\b", clause):
                found.append((m.start(), name))
    return found


# --------------------------------------------------------------------------- target and destination

_VERB_RE = re.compile(r"\b(?P<verb>" + "|".join(re.escape(v) for v in sorted(TASK_VERBS, key=len, reverse=True))
                      + r")\b(?P<part>\s+(?:up|out|down|me|us|over|along|back))?\s+")


def _strip_location(text: str, plain: bool) -> str:
    """Drop a relative clause / locator right at the start of `text` ("that is on the counter next to the sink",
    "from the table"), returning what follows it. `plain`: a bare "on/in/at the X" is a location too (after a
    carry verb: "take the cup on the table to the sink")."""
    marked = r"(?:(?:that|which|who|that's|sitting|lying|resting|located|standing|placed|kept|found|seen|waiting)\b)"
    m = re.match(r"\s*,?\s*(?:" + _LOCATOR_MARK + _AT + "|" + _FROM + ")" + r"\s+(?:the |a |an |that |this |my )?"
                 r"([a-z][a-z \-]*?)(?=\s*(?:,|\.|;|$|\b(?:and|then|onto|into|to|over|across|on top of|atop|upon|back|"
                 r"so|please|on|in|inside|at|next to|near|beside|by)\b))", text)
    if not m:
        return text
    head = text[: m.end()]
    if not plain and not re.match(r"\s*,?\s*(?:" + marked + "|" + _FROM + ")", head):
        return text
    rest = text[m.end():]
    return _strip_location(rest, plain) if rest != text else rest


def _destination_after(text: str, verb: str) -> str | None:
    """The destination named right after an object: "onto the counter next to the sink" -> counter."""
    text = re.sub(r"^\s*(?:off|down|back|over|up|away)\s+(?=(?:on|in|onto|into|to|at|inside|atop|upon)\b)", " ", text)
    text = _strip_location(text, verb in _CARRY_VERBS)
    text = re.sub(r"^\s*,?\s*(?:and\s+)?(?:then\s+)?", "", text)
    preps = _STRONG_PREP if verb in _CARRY_VERBS and verb not in ("move",) else _STRONG_PREP + "|" + _WEAK_PREP
    m = re.match(r"(?:(?:it|them)\s+)?(?:down\s+|back\s+|over\s+|up\s+|off\s+)?(?:" + preps + r")\s+(?P<np>.*)", text)
    if not m:
        return None
    return _dest_np(m.group("np"))


def _dest_np(text: str) -> str | None:
    np_ = noun_phrase(text)
    if np_:  # "on the table in the sink": a second place-preposition after the first names the destination
        tail = text[text.find(np_.split()[-1]) + len(np_.split()[-1]):]
        later = re.match(r"\s*(?:onto|into|in|on|inside|on top of|atop|upon)\s+(?P<np>[a-z][a-z \-]*)", tail)
        if later and noun_phrase(later.group("np")):
            np_ = noun_phrase(later.group("np"))
    if not np_ or np_ in _NOT_DESTINATION or text.strip().startswith(("me", "here", "us", "you")):
        return None
    return singular(np_)


_PLACE_CLAUSE = re.compile(r"\b(?:put|place|set|drop|deposit|leave|lay|rest|position|stick|stash|stow|plop|pop|park|"
                           r"transfer|relocate|move|carry|take|bring|deliver|return|unload|shift|"
                           r"get(?=\s+(?:it|them|that|this)\b))\b"  # "get it to the shelf", not "get to"
                           r"(?:\s+(?:it|them|that one|this one|that|this|the object|the item|the thing|one))?"
                           r"(?:\s+(?:down|back|over|off|up|right|away))?\s+(?P<prep>" + _STRONG_PREP + "|" + _WEAK_PREP
                           + r")\s+(?=(?P<np>[a-z][a-z \-]*))")  # a lookahead: the next clause is searched too


_NOT_OBJECTS = {"room", "area", "house", "kitchen", "picture", "photo", "look", "break", "nap", "seat", "off",
                "selfie", "walk", "note", "step", "turn", "moment", "second", "minute", "while", "way", "rest",
                "flight",
                "song", "joke", "breath", "care", "position", "altitude", "height", "hold"}


def _object_np(rest: str) -> str | None:
    """The object phrase after a task verb, or None when what follows is no object (a pronoun, a direction,
    "two steps forward", "a picture")."""
    np_ = noun_phrase(rest)
    if not np_ or np_ in _PRONOUNS or np_ in _DIRS or np_.split()[0] in _DIRS or np_.split()[0] in _NUM_WORDS:
        return None
    if not_an_object(np_) or np_.split()[0] in TASK_VERBS:
        return None
    return np_


def not_an_object(np_: str) -> bool:
    """A phrase whose head noun no room holds as a thing ("your time", "a bit", "the answer"): never a target."""
    head = singular(np_).split()[-1] if np_.split() else ""
    return head in _NOT_OBJECTS or object_noun(head) is False


def _is_action(clause: str) -> bool:
    """A clause with a task verb acting on an object (or a pronoun standing for one)."""
    for m in _VERB_RE.finditer(clause + " "):
        rest = clause[m.end():]
        if _object_np(rest) or re.match(r"(?:it|them|that|this)\b", rest.strip()) or noun_phrase(rest) == "one":
            return True
    return False


def _object_and_destination(c: str, plan: Plan) -> str | None:
    """Target and destination from the task verbs; returns the first task verb seen (None when there is none)."""
    first_verb = None
    for m in _VERB_RE.finditer(c):
        verb = m.group("verb")
        rest = c[m.end():]
        np_ = _object_np(rest)
        if np_ is None:
            if re.match(r"(?:it|them|that|this)\b", rest.strip()) or noun_phrase(rest) in ("", "one"):
                first_verb = first_verb or verb
            continue
        first_verb = first_verb or verb
        if plan.target is None and not plan.choices and not plan.category and not plan.selector:
            if np_ in CATEGORY_WORDS or singular(np_) in CATEGORY_WORDS:
                plan.category = singular(np_)
            else:
                plan.target = singular(np_)
        last = np_.split()[-1]
        after = rest[rest.find(last) + len(last):]
        if plan.destination is None:  # a verb that does not place takes only a strong preposition ("onto")
            plan.destination = _destination_after(after, verb if verb in PLACE_VERBS else "carry")
        if plan.target or plan.category or plan.choices or plan.selector:
            break
    if plan.destination is None:
        for m in _PLACE_CLAUSE.finditer(c):
            dest = _dest_np(m.group("np"))
            if dest and dest != plan.target and not _is_location_only(c, m):
                plan.destination = dest
    return first_verb


def _is_location_only(c: str, m: re.Match) -> bool:
    """"take the cup on the table": a carry verb with a plain on/in and an object named right before it."""
    weak = re.fullmatch(_WEAK_PREP, m.group("prep")) is not None
    carry = re.match(r"\b(?:take|bring|carry|get|deliver|return)\b", c[m.start():]) is not None
    pronoun = re.match(r"\b[a-z]+\s+(?:it|them|that|this)\b", c[m.start():]) is not None
    return weak and carry and not pronoun


def _antecedent(c: str) -> str | None:
    """For "I lost my purple cup somewhere; find it": the first object-like phrase after a possessive or article."""
    for m in re.finditer(r"\b(?:my|the|a|an|our|your)\s+([a-z][a-z \-]*)", c):
        np_ = noun_phrase(m.group(1))
        if np_ and np_ not in ("room", "area", "house", "kitchen", "place", "floor", "way", "moment", "time") \
                and not not_an_object(np_) and np_ not in _PRONOUNS and np_.split()[0] not in _DIRS:
            return singular(np_)
    return None


# --------------------------------------------------------------------------- the reader


def parse_command(command: str, skills: list[str] | tuple[str, ...] = ()) -> Plan:
    """Read the plan out of a command; `skills` (the live library's policy skills) lets a command name a
    registered skill outright. A command with nothing to do is returned with understood=False and the reason."""
    plan = Plan()
    c = normalize(command)
    if not c.strip(" .!?"):
        return _refuse(plan, "the command is empty")
    c = _conditional(c, plan)
    c = _exclusions(c, plan)
    _selector(c, plan)
    if plan.selector:  # the phrase with the size word names the group, not a target
        plan.target = None
    clauses = [x.strip() for x in re.split(r"[,;!?]|\.(?!\d)|\band then\b|\bthen\b|\bafter that\b|"
                              r"\bafterwards\b|\band\b|"
                                         r"\bnext\b|\bfinally\b|\bfirst\b|\bbefore\b", c) if x.strip()]
    verb = _object_and_destination(c, plan)
    for clause in clauses:
        named = _named_skills(clause, skills)
        if named:
            plan.motions.extend(name for _pos, name in sorted(named))
            continue
        if _is_action(clause):
            continue
        plan.motions.extend(motions(clause))
    if verb and not (plan.target or plan.choices or plan.category or plan.selector) \
            and re.search(r"\b(?:it|them)\b", c):
        plan.target = _antecedent(c)
    if plan.target and plan.target.endswith(" one") and plan.excluded:  # "not the red cup; the purple one"
        plan.target = f"{plan.target[:-4]} {plan.excluded[0].split()[-1]}"
    head = (plan.target or plan.group or "").split()[-1:]
    plan.excluded = [f"{x[:-4]} {head[0]}" if x.endswith(" one") and head else x for x in plan.excluded]
    if plan.choices:
        plan.target = None
    if plan.category and plan.target is None and plan.excluded and plan.category in plan.excluded:
        plan.category = None
    if verb is None and not (plan.target or plan.choices or plan.category or plan.selector or plan.motions):
        _telegraphic(c, plan)
    return _judge(plan, verb, command)


_TELEGRAPHIC = re.compile(r"^\s*(?:the |a |an |my |that |this )?(?P<x>[a-z][a-z0-9 \-]*?)\s*(?:(?:,\s*)?\b(?P<prep>"
                          + _STRONG_PREP + "|" + _WEAK_PREP + r"|over)\s+(?P<y>[a-z][a-z0-9 \-]*?))?[\s,.!?;:]*$")


def _telegraphic(c: str, plan: Plan) -> None:
    """A command without a verb: "red cup to the table", "the banana on the shelf please", "the apple, please".
    Read as pick up (and place), when the object named is something a room holds (a known physical noun; an
    unknown one only with a known destination), and said so in `plan.note`."""
    m = _TELEGRAPHIC.match(c)
    if not m:
        return
    x = noun_phrase(m.group("x"))
    if not x or x != " ".join(m.group("x").split()) or x in _PRONOUNS or not_an_object(x):
        return
    dest = _dest_np(m.group("y")) if m.group("y") else None
    if m.group("y") and (dest is None or noun_phrase(m.group("y")) != " ".join(m.group("y").split()[
            1 if m.group("y").split()[0] in _DET else 0:])):
        return
    known = object_noun(singular(x).split()[-1]) is True
    if not known and not (dest and object_noun(dest.split()[-1]) is True):
        return
    if x in CATEGORY_WORDS or singular(x) in CATEGORY_WORDS:
        plan.category = singular(x)
    else:
        plan.target = singular(x)
    plan.destination = dest
    plan.note = (f"The command has no task verb; I read it as: pick up the {plan.target or plan.category}"
                 + (f" and place it on the {dest}." if dest else "."))


def _judge(plan: Plan, verb: str | None, command: str) -> Plan:
    if plan.target or plan.choices or plan.category or plan.selector or plan.motions:
        return plan
    if plan.destination:
        return _refuse(plan, f"the command says where to put something ({plan.destination}) but names no object")
    if verb:
        return _refuse(plan, f"the command asks to {verb} but names no object I can look for")
    return _refuse(plan, f"I cannot understand {command.strip()!r}: it names no object to pick up or place, no "
                         "motion, and no task verb I know (pick up, grab, fetch, find, put, place, move, turn...)")


def _refuse(plan: Plan, reason: str) -> Plan:
    plan.understood = False
    plan.reason = reason
    plan.target = plan.destination = plan.selector = plan.group = plan.category = None
    plan.motions, plan.choices, plan.excluded = [], [], []
    return plan
