"""coapkb: distributed semantic knowledge bases for robot teams, over CoAP/UDP.

Each robot serves one module of the team's knowledge base and answers its
teammates' SPARQL queries with compact CBOR.  Modules map onto the seed
paper's Fig. 2: ``knowledge_base`` (KB), ``config`` (Configuration),
``agent.controller`` (Controller), ``agent.query_handler`` (Query Handler),
``agent.task_assigner`` (Task Assigner), ``agent.task_executor`` (Task
executor) and ``transport`` (Communication).
"""

__version__ = "0.1.0"
