"""The robot agent, one module per component of the seed's Fig. 2:

========================  =====================================
Knowledge Base            :mod:`coapkb.kb.store`
Configuration             :mod:`coapkb.config`
Controller                :mod:`coapkb.agent.controller`
Query Handler             :mod:`coapkb.agent.query_handler`
Task Assigner             :mod:`coapkb.agent.task_assigner`
Task executor             :mod:`coapkb.agent.task_executor`
Communication             :mod:`coapkb.transport` (server and client)
========================  =====================================

:mod:`coapkb.agent.robot` wires them into one running robot.
"""
